"""The effect interface: parsing, XML wiring, and the range-noise laws in sampler and likelihood."""

import mitsuba as mi
import numpy as np
import pytest

import mi_lidar
from mi_lidar.core.effects import RangeNoise, parse_effects
from mi_lidar.core.elements import ElementTable
from mi_lidar.core.likelihood import mixture_log_likelihood
from mi_lidar.core.trace import trace_rounds

from .conftest import SCENES, rays_along_x


def test_parse_effects_round_trip():
    effects = parse_effects("range_noise(law=proportional, sigma0=0.005, k=0.001), range_noise(sigma0=0.02)")
    assert [e.describe() for e in effects] == [
        "range_noise(law=proportional, sigma0=0.005, k=0.001)",
        "range_noise(law=constant, sigma0=0.02)",  # k does not exist under the constant law
    ]
    assert parse_effects("") == []


@pytest.mark.parametrize(
    "law,sigma0,k,expected",
    [
        ("constant", 0.05, 0.0, np.sqrt(0.005**2 + 0.05**2)),
        ("proportional", 0.0, 0.01, np.sqrt(0.005**2 + (0.01 * 8.0) ** 2)),
        ("physics", 0.0, 1e-4, np.sqrt(0.005**2 + 1e-4 * 64.0)),
    ],
)
def test_range_noise_law_in_simulation(law, sigma0, k, expected):
    # Wall at 8 m behind transparent layers (p = 0), facing the sensor: cos(incidence) > 0.99 near the centre, so r
    # is 8 m within 1%.
    scene = mi_lidar.load_scene(SCENES / "permeable_layers.xml", p1=0.0, p2=0.0, p3=0.0)
    model, pose = mi_lidar.scene.scene_sensor_model(scene)
    model.effects = [RangeNoise(law=law, sigma0=sigma0, k=k)]
    logs = [mi_lidar.simulate(scene, "raster", model=model, seed=s) for s in range(3)]
    centre = np.concatenate(
        [(log.ranges - log.attributes["nominal_range"])[0][log.attributes["cos_incidence"][0] > 0.99] for log in logs]
    )
    assert len(centre) > 2000
    # Sample std of >2000 Gaussian draws: relative standard error < 1.6%; allow 6%.
    assert abs(centre.std() / expected - 1) < 0.06


def test_effects_from_xml_are_traversed(tmp_path):
    text = (
        (SCENES / "permeable_layers.xml")
        .read_text()
        .replace(
            '<integer name="max_segments" value="8"/>',
            '<integer name="max_segments" value="8"/><string name="effects" value="range_noise(sigma0=0.03)"/>',
        )
    )
    path = tmp_path / "scene.xml"
    path.write_text(text)
    scene = mi_lidar.load_scene(path)
    params = mi.traverse(scene.integrator())
    assert "effects.range_noise.sigma0" in params
    assert abs(params["effects.range_noise.sigma0"][0] - 0.03) < 1e-7


def test_likelihood_matches_pass_through_mixture():
    # Layers p = (0.3, 0.5, 0.2) at 2, 4, 6 m and a wall at 8 m, sigma 0.005 m; rays along +x.
    scene = mi_lidar.load_scene(SCENES / "permeable_layers.xml")
    model, _ = mi_lidar.scene.scene_sensor_model(scene)
    table = ElementTable.from_scene(scene)
    n = 4
    rays = rays_along_x(n)
    rounds = trace_rounds(scene, table, model, rays)
    z = mi.Float([4.001, 8.0, 0.0, 5.0])
    hit = mi.Bool([True, True, False, True])
    ll = np.asarray(mixture_log_likelihood(table, model, rays, rounds, z, hit))
    s = 0.005
    gauss = lambda x: -0.5 * (x / s) ** 2 - np.log(s * np.sqrt(2 * np.pi))  # noqa: E731
    assert abs(ll[0] - (np.log(0.7 * 0.5) + gauss(0.001))) < 1e-3
    assert abs(ll[1] - (np.log(0.7 * 0.5 * 0.8) + gauss(0.0))) < 1e-3
    assert ll[2] < -25  # the wall is opaque: a miss is (numerically) impossible
    assert ll[3] < -1e4  # 5 m is 200 sigma from every element
