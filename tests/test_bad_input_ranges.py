"""Range noise and distances outside their limits get a clear error that names the value, the limit and the fix."""

import re

import numpy as np
import pytest

import mi_lidar
from mi_lidar.core.effects import parse_effects
from mi_lidar.core.errors import ParameterError, SceneError

from .scene_text import scene_xml, write


def test_negative_sigma(tmp_path):
    body = (
        '<shape type="sphere" id="ball"><bsdf type="lidar_material">'
        '<float name="range_sigma" value="-0.01"/></bsdf></shape>'
    )
    with pytest.raises(SceneError, match=r"range_sigma=-0.01"):
        mi_lidar.load_scene(write(tmp_path, scene_xml(body)))


def test_negative_sensor_sigma_and_bad_ranges(tmp_path):
    text = scene_xml("").replace(
        "</sensor>", '<float name="min_range" value="5"/><float name="max_range" value="2"/></sensor>'
    )
    with pytest.raises(SceneError, match=r"min_range=5.0, max_range=2.0"):
        mi_lidar.load_scene(write(tmp_path, text))


@pytest.mark.parametrize(
    "where, expected",
    [
        ("sensor", "lidar sensor: range_sigma=inf m is outside [0, 1000] m (a range noise beyond 1000 m is a misread"),
        ("material", "lidar_material: range_sigma=inf m is outside [0, 1000] m"),
        ("effect", "effect 'range_noise': sigma0=inf m is outside [0, 1000] (constant part of the noise)"),
    ],
)
def test_an_infinite_range_sigma_is_refused(tmp_path, where, expected):
    """The sensor and the material took range_sigma=inf and rendered scans of infinite ranges; the effect refused
    sigma0=inf saying it was outside [0, inf]."""
    inf = '<float name="range_sigma" value="inf"/>'
    text = {
        "sensor": scene_xml("").replace("</sensor>", inf + "</sensor>"),
        "material": scene_xml(f'<shape type="sphere"><bsdf type="lidar_material">{inf}</bsdf></shape>'),
        "effect": scene_xml(
            '<integrator type="lidar_integrator"><string name="effects" value="range_noise(sigma0=inf)"/></integrator>'
        ),
    }[where]
    with pytest.raises(SceneError) as error:
        mi_lidar.load_scene(write(tmp_path, text))
    assert expected in str(error.value), error.value


@pytest.mark.parametrize(
    "where, value, expected",
    [
        ("max_range", "1e30", "lidar sensor: max_range=1e+30 m is outside [0, 1e+08] m"),
        ("min_range", "2e8", "lidar sensor: min_range=2e+08 m is outside [0, 1e+08] m"),
        ("range_sigma", "1e30", "lidar sensor: range_sigma=1e+30 m is outside [0, 1000] m"),
        ("material", "1e30", "lidar_material: range_sigma=1e+30 m is outside [0, 1000] m"),
    ],
)
def test_an_absurd_distance_or_range_noise_in_a_scene_is_refused(tmp_path, where, value, expected):
    """The sensor took max_range=1e30 and range_sigma=1e30 (a room scanned with 12 returns of 360: the others were
    drawn outside the range window), and the material range_sigma=1e30, without a word."""
    prop = "range_sigma" if where == "material" else where
    element = f'<float name="{prop}" value="{value}"/>'
    if where == "min_range":
        element += '<float name="max_range" value="3e8"/>'
    text = (
        scene_xml(f'<shape type="sphere"><bsdf type="lidar_material">{element}</bsdf></shape>')
        if where == "material"
        else scene_xml("").replace("</sensor>", element + "</sensor>")
    )
    with pytest.raises(SceneError) as error:
        mi_lidar.load_scene(write(tmp_path, text))
    assert expected in str(error.value) and "a misread number); fix the value in the scene" in str(error.value)
    if where != "material":  # a scene dict goes through the same plugin
        scene = {"type": "scene", "sensor": {"type": "lidar", "pattern": "planar-180", prop: float(value)}}
        if where == "min_range":
            scene["sensor"]["max_range"] = 3e8
        with pytest.raises(SceneError, match=re.escape(expected)):
            mi_lidar.load_scene(scene)


@pytest.mark.parametrize(
    "values, expected",
    [
        ({"max_range": 1e30}, "sensor model: max_range=1e+30 m is outside [0, 1e+08] m, or inf for no far end"),
        ({"min_range": 2e8, "max_range": np.inf}, "sensor model: min_range=2e+08 m is outside [0, 1e+08] m"),
        ({"range_sigma": 1e30}, "sensor model: range_sigma=1e+30 m is outside [0, 1000] m"),
        ({"range_sigma": np.inf}, "sensor model: range_sigma=inf m is outside [0, 1000] m (a range noise beyond"),
    ],
)
def test_a_sensor_model_refuses_absurd_distances_and_range_noise(values, expected):
    from mi_lidar.core.sensor_model import SensorModel

    with pytest.raises(ParameterError, match=re.escape(expected)):
        SensorModel(**values)
    assert SensorModel(max_range=np.inf).max_range == np.inf  # no far end of the range window (planar models)


@pytest.mark.parametrize(
    "spec, expected",
    [
        ("range_noise(sigma0=1e30)", "effect 'range_noise': sigma0=1e+30 m is outside [0, 1000]"),
        ("corner_returns(sigma=1e30)", "effect 'corner_returns': sigma=1e+30 m is outside [0, 1000]"),
        ("physics(sigma0=1e30)", "density 'physics': sigma0=1e+30 m is outside [0, 1000]"),
    ],
)
def test_effects_and_densities_refuse_an_absurd_range_noise(spec, expected):
    from mi_lidar.core.densities import parse_density

    parse = parse_density if spec.startswith("physics") else parse_effects
    with pytest.raises(ParameterError, match=re.escape(expected)):
        parse(spec)


def test_per_element_range_noise_beyond_the_limit_is_refused(tmp_path):
    """A PLY face property range_sigma_0 of 1e30 m was taken without a word."""
    from mi_lidar.scene.files import write_mesh_ply

    vertices = np.array([[5.0, -5, -5], [5, 5, -5], [5, 0, 5]])
    faces = np.array([[0, 1, 2], [0, 2, 1]])
    write_mesh_ply(tmp_path / "m.ply", vertices, faces, range_sigma=np.array([0.02, 1e30]))
    body = '<shape type="ply" id="ground"><string name="filename" value="m.ply"/></shape>'
    with pytest.raises(SceneError) as error:
        mi_lidar.simulate(mi_lidar.load_scene(write(tmp_path, scene_xml(body))), "planar-180")
    assert str(error.value) == (
        "shape 'ground': range_sigma=1e+30 m (1 of 2 values) is outside [0, 1000] m (a range noise beyond 1000 m is "
        "a misread number); fix the material or the PLY face property"
    )


@pytest.mark.parametrize(
    "sigmas, expected",
    [
        ([-0.5, -1e30, 0.02], "range_sigma=-0.5 m (2 of 3 values) is outside [0, 1000] m (a range noise beyond"),
        ([np.nan, np.inf], "range_sigma=inf m (1 of 2 values) is outside [0, 1000] m (a range noise beyond"),
    ],
)
def test_per_element_range_noise_below_zero_or_infinite_reads_the_same_message(sigmas, expected):
    """A negative per-element range_sigma had a message of its own, without the allowed range, the count or the fix;
    NaN (the element takes the sensor's range_sigma) still passes."""
    from mi_lidar.core.scene_shapes import check_element_values

    with pytest.raises(SceneError) as error:
        check_element_values("ground", "range_sigma", np.array(sigmas))
    message = str(error.value)
    assert message.startswith(f"shape 'ground': {expected}"), message
    assert message.endswith("; fix the material or the PLY face property"), message
    check_element_values("ground", "range_sigma", np.array([np.nan, 0.0, 1000.0]))


def test_a_negative_sensor_range_sigma_reads_one_message_with_its_range_and_fix(tmp_path):
    """The sensor checked range_sigma twice: a negative or infinite one was refused by its own message, without the
    allowed range's upper end or the fix, before the limit check."""
    text = scene_xml("").replace("</sensor>", '<float name="range_sigma" value="-0.01"/></sensor>')
    with pytest.raises(SceneError) as error:
        mi_lidar.load_scene(write(tmp_path, text))
    assert (
        "lidar sensor: range_sigma=-0.01 m is outside [0, 1000] m (a range noise beyond 1000 m is a misread number); "
        "fix the value in the scene"
    ) in str(error.value), error.value
