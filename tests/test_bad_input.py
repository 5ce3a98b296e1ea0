"""Bad input gets a clear error that names the value and the fix."""

import re

import numpy as np
import pytest

import mi_lidar
from mi_lidar.core.effects import parse_effects
from mi_lidar.core.errors import ParameterError, PatternError, PoseError, SceneError
from mi_lidar.core.poses import validate_poses

from .conftest import SCENES
from .scene_text import scene_xml, write


def test_unknown_pattern_names_the_pattern_and_choices():
    with pytest.raises(PatternError, match=r"velodyne-99.*vlp16"):
        mi_lidar.simulate(mi_lidar.load_scene(SCENES / "indoor_planar.xml"), "velodyne-99")


def test_unknown_pattern_in_xml(tmp_path):
    text = scene_xml("").replace("planar-180", "no-such-lidar")
    with pytest.raises(SceneError, match="no-such-lidar"):
        mi_lidar.load_scene(write(tmp_path, text))


@pytest.mark.parametrize("value", ["1.5", "-0.1"])
def test_hit_probability_outside_unit_interval(tmp_path, value):
    body = (
        f'<shape type="sphere" id="ball"><bsdf type="lidar_material">'
        f'<float name="p_hit" value="{value}"/></bsdf></shape>'
    )
    with pytest.raises(SceneError, match=rf"p_hit={float(value)}.*\[0, 1\]"):
        mi_lidar.load_scene(write(tmp_path, scene_xml(body)))


@pytest.mark.parametrize(
    "prop, message",
    [
        ('<string name="max_range" value="far"/>', "lidar sensor: max_range='far' is not a number; write <float"),
        ('<float name="firings" value="2.5"/>', "lidar sensor: firings=2.5 is not a whole number"),
    ],
)
def test_a_sensor_property_of_the_wrong_kind_is_named(tmp_path, prop, message):
    """Python's words came without the property ('could not convert string to float: 'far''); 2.5 firings read as 2."""
    with pytest.raises(SceneError, match=re.escape(message)):
        mi_lidar.load_scene(write(tmp_path, scene_xml("").replace("</sensor>", f"{prop}</sensor>")))


def test_malformed_xml(tmp_path):
    with pytest.raises(SceneError, match="scene.xml"):
        mi_lidar.load_scene(write(tmp_path, '<scene version="3.0.0"><shape type="sphere"></scene>'))


def test_unknown_property_is_named(tmp_path):
    body = (
        '<shape type="sphere" id="ball"><bsdf type="lidar_material"><float name="p_hitt" value="0.5"/></bsdf></shape>'
    )
    with pytest.raises(SceneError, match="p_hitt"):
        mi_lidar.load_scene(write(tmp_path, scene_xml(body)))


def test_integrator_named_like_the_sensor_gets_a_hint(tmp_path):
    text = scene_xml('<integrator type="lidar"/>')
    with pytest.raises(SceneError, match="lidar_integrator"):
        mi_lidar.load_scene(write(tmp_path, text))


def test_missing_scene_file(tmp_path):
    with pytest.raises(SceneError, match="no such scene file"):
        mi_lidar.load_scene(tmp_path / "absent.xml")


def test_nan_pose():
    pose = np.eye(4)
    pose[0, 3] = np.nan
    with pytest.raises(PoseError, match="pose 0 is not a rigid transform: has non-finite entries"):
        validate_poses(pose)


def test_non_rigid_pose():
    pose = np.diag([2.0, 1.0, 1.0, 1.0])
    with pytest.raises(PoseError, match="pose 1 is not a rigid transform"):
        validate_poses(np.stack([np.eye(4), pose]))


def test_simulate_rejects_bad_pose_before_tracing():
    scene = mi_lidar.load_scene(SCENES / "indoor_planar.xml")
    with pytest.raises(PoseError):
        mi_lidar.simulate(scene, "planar-180", poses=np.full((4, 4), np.nan))


@pytest.mark.parametrize(
    "spec,match",
    [
        ("no_such_effect()", "unknown effect 'no_such_effect'"),
        ("range_noise(law=cubic)", "law='cubic'"),
        ("range_noise(sigma0=-1)", "sigma0=-1"),
        ("range_noise(sigmaa=1)", r"unknown parameter\(s\) \['sigmaa'\]"),
        ("range_noise(sigma0=1", "missing '\\)'"),
    ],
)
def test_bad_effect_specs(spec, match):
    with pytest.raises(ParameterError, match=match):
        parse_effects(spec)


def test_max_segments_out_of_range(tmp_path):
    text = scene_xml('<integrator type="lidar_integrator"><integer name="max_segments" value="0"/></integrator>')
    with pytest.raises(SceneError, match="max_segments=0"):
        mi_lidar.load_scene(write(tmp_path, text))


def _denied(path):
    raise PermissionError(13, "Permission denied", str(path))


@pytest.mark.parametrize(
    "reader", ["spec", "mesh", "library index", "primitive", "pattern csv", "pattern npy", "ouster metadata"]
)
def test_a_file_the_process_may_not_read_is_named_as_such(reader, tmp_path, monkeypatch):
    """A permission error was reported as a parse error ('cannot parse the spec: [Errno 13] ...', 'not a triangle
    mesh PLY (PermissionError ...)', 'not a primitive library index'): each reader now says the file cannot be read
    and how to make it readable. The read is denied by the test (file modes do not bind a root process)."""
    import json
    import pathlib
    import re

    from mi_lidar.core.errors import SpecError
    from mi_lidar.dataset.spec import read_spec_file
    from mi_lidar.hybrid import blocks, primitives

    path = tmp_path / {"spec": "spec.yaml", "mesh": "ground.ply"}.get(reader, "library.json")
    path.write_text("{}")
    if reader == "spec":
        monkeypatch.setattr(pathlib.Path, "read_text", lambda self, *a, **k: _denied(self))
        call, error = (lambda: read_spec_file(path)), SpecError
    elif reader == "mesh":
        monkeypatch.setattr(blocks.PlyData, "read", _denied)
        call, error = (lambda: blocks.read_mesh_ply(path)), SceneError
    elif reader.startswith(("pattern", "ouster")):  # were 'check the path', 'not a plain numeric NPY array
        # (PermissionError ...)' and 'pass the sensor's metadata JSON': the path and the file were right
        from mi_lidar.core.patterns import from_table
        from mi_lidar.core.patterns.ouster_sensor import read_ouster_metadata

        path = tmp_path / {"pattern csv": "p.csv", "pattern npy": "p.npy"}.get(reader, "meta.json")
        path.write_text("")
        monkeypatch.setattr(pathlib.Path, "open", lambda self, *a, **k: _denied(self))
        monkeypatch.setattr(pathlib.Path, "read_text", lambda self, *a, **k: _denied(self))
        monkeypatch.setattr(np, "load", lambda p, **k: _denied(p))
        call, error = (
            (lambda: (read_ouster_metadata if reader == "ouster metadata" else from_table)(path)),
            PatternError,
        )
    else:
        path.write_text(json.dumps({"primitives": [{"id": "a", "label": 1, "file": "a.npz"}]}))
        if reader == "library index":
            monkeypatch.setattr(pathlib.Path, "read_text", lambda self, *a, **k: _denied(self))
        else:
            path = tmp_path / "a.npz"
            path.write_bytes(b"")
            monkeypatch.setattr(primitives.np, "load", lambda p, **k: _denied(p))
        call, error = (lambda: primitives.PrimitiveLibrary.load(tmp_path)), SceneError
    with pytest.raises(error, match=rf"{re.escape(str(path))}: cannot read the .* \(permission denied\); make it"):
        call()


PLY_HEADER = "ply\nformat ascii 1.0\nelement vertex {v}\nproperty float x\nproperty float y\nproperty float z\n"
PLY_FACES = "element face 0\nproperty list uchar int vertex_indices\nend_header\n"


@pytest.mark.parametrize(
    "body,expected",
    [
        # a Python plugin's refusal: Mitsuba passed on the whole traceback as the message
        (
            '<integrator type="lidar_integrator"><string name="effects" value="range_bias(bias=abc)"/></integrator>',
            'failed to instantiate integrator plugin of type "lidar_integrator": effect '
            "'range_bias': bias='abc' is not a number",
        ),
        (
            '<shape type="sphere"><bsdf type="lidar_material"><integer name="label" value="-3"/></bsdf></shape>',
            "lidar_material: label=-3 is outside [0, 2**24 = 16777216] (float32's whole numbers); fix the value",
        ),
        # labels travel in float32 channels: 16777217 was reported as 16777216, 2**31 as -2**31, and 99999999999
        # failed inside Dr.Jit's render ('error while performing a custom differentiable operation'); 1.5 read as 1
        (
            '<shape type="sphere"><bsdf type="lidar_material"><integer name="label" value="16777217"/></bsdf></shape>',
            "lidar_material: label=16777217 is outside [0, 2**24 = 16777216]",
        ),
        # a <float> where a count belongs was truncated (label 1.5 -> 1, max_segments 4.5 -> 4); a <string> where a
        # number belongs failed with Python's words ('could not convert string to float: 'half''), no property named
        (
            '<shape type="sphere"><bsdf type="lidar_material"><float name="label" value="1.5"/></bsdf></shape>',
            'lidar_material: label=1.5 is not a whole number; write <integer name="label" .../>',
        ),
        (
            '<integrator type="lidar_integrator"><float name="max_segments" value="4.5"/></integrator>',
            "lidar integrator: max_segments=4.5 is not a whole number",
        ),
        (
            '<shape type="sphere"><bsdf type="lidar_material"><string name="p_hit" value="half"/></bsdf></shape>',
            'lidar_material: p_hit=\'half\' is not a number; write <float name="p_hit" value="..."/>',
        ),
        # a sensor pose with NaN was rendered as a scan of NaN rays
        ("", "lidar sensor: to_world: pose 0 is not a rigid transform: has non-finite entries"),
        # Mitsuba's words on meshes without faces or vertices were Dr.Jit's ('operands have incompatible sizes')
        (
            '<shape type="ply"><string name="filename" value="{faceless}"/></shape>',
            "a mesh without faces gives this: give the shape at least one triangle, or remove it",
        ),
        (
            '<shape type="ply"><string name="filename" value="{empty}"/></shape>',
            "a mesh without vertices gives this: give the shape at least one triangle, or remove it",
        ),
        # a binary file given as a PLY: Mitsuba's message quoted its bytes, and Python's UTF-8 decoder replaced it
        (
            '<shape type="ply"><string name="filename" value="{binary}"/></shape>',
            'binary.ply": invalid PLY header: unknown token "\\xff\\xfe',
        ),
    ],
)
def test_a_scene_mitsuba_refuses_is_one_line_naming_the_cause(tmp_path, body, expected):
    """Each error was several lines (a Python traceback, Mitsuba's source location) or another error's words."""
    names = {name: tmp_path / f"{name}.ply" for name in ("faceless", "empty", "binary")}
    names["faceless"].write_text(PLY_HEADER.format(v=3) + PLY_FACES + "0 0 0\n1 0 0\n0 1 0\n")
    names["empty"].write_text(PLY_HEADER.format(v=0) + PLY_FACES)
    names["binary"].write_bytes(b"ply\n\xff\xfe\x00garbage\n")
    text = scene_xml(body.format(**names))
    if not body:
        text = text.replace("</sensor>", '<transform name="to_world"><translate x="nan"/></transform></sensor>')
    with pytest.raises(SceneError) as error:
        mi_lidar.load_scene(write(tmp_path, text))
    message = str(error.value)
    assert message.startswith(f"{tmp_path / 'scene.xml'}: could not load the scene: "), message
    assert "\n" not in message and "Traceback" not in message, message
    assert "(line 1, col " in message and ".cpp:" not in message and ".h:" not in message, message
    assert expected in message, message


@pytest.mark.parametrize("reader", ["density", "pattern", "log", "primitive"])
def test_random_bytes_for_a_numpy_file_are_not_called_a_pickle(reader, tmp_path):
    """numpy reads a file that is neither .npy nor .npz as a pickle and advised to 'load it unsafely using the
    `allow_pickle=` keyword': each reader of a numpy file now says the file is damaged or of another format."""
    import json

    from mi_lidar.core.densities.tables import load_density
    from mi_lidar.core.errors import MiLidarError
    from mi_lidar.core.log import Log
    from mi_lidar.core.patterns import get_pattern
    from mi_lidar.hybrid.primitives import PrimitiveLibrary

    path = tmp_path / ("a.npy" if reader == "pattern" else "a.npz")
    path.write_bytes(np.random.default_rng(0).bytes(1000))
    (tmp_path / "library.json").write_text(json.dumps({"primitives": [{"id": "a", "label": 1, "file": "a.npz"}]}))
    calls = {
        "density": lambda: load_density(path),
        "pattern": lambda: get_pattern(path),
        "log": lambda: Log.load(path),
        "primitive": lambda: PrimitiveLibrary.load(tmp_path),
    }
    with pytest.raises(MiLidarError) as error:
        calls[reader]()
    message = str(error.value)
    assert str(path) in message and "allow_pickle" not in message, message
    assert "its first bytes are neither a numpy .npy header nor a zip archive: damaged, or another format" in message


@pytest.mark.parametrize(
    "scale, quaternion", [(np.nan, [0, 0, 0, 1]), (0.0, [0, 0, 0, 1]), (-0.1, [0, 0, 0, 1]), (0.1, [0, 0, 0, 2])]
)
def test_an_ellipsoid_without_a_finite_positive_scale_is_refused(scale, quaternion):
    """Such an element was never met, silently (Mitsuba skips it; a scale of 0 would divide by zero in its chord), or,
    with a quaternion that is not a unit one, met where Mitsuba's shape and mi-lidar's chords disagree; now the
    scene is refused, naming the element and its values."""
    import mitsuba as mi

    scales = np.array([[0.2, 0.2, 0.2], [0.1, 0.1, scale]], np.float32)
    tensor = lambda a: mi.TensorXf(np.asarray(a, np.float32))  # noqa: E731
    scene = {
        "type": "scene",
        "bushes": {
            "type": "ellipsoids",
            "centers": tensor([[5, 0, 0], [8, 0, 0]]),
            "scales": tensor(scales),
            "quaternions": tensor([[0, 0, 0, 1], quaternion]),
        },
    }
    with pytest.raises(
        SceneError, match=r"'bushes': ellipsoid 1 \(of 2, 1 such\).*finite scales > 0 m and a unit quaternion"
    ):
        mi_lidar.simulate(mi_lidar.load_scene(scene), "planar-180")


@pytest.mark.parametrize(
    "place, message",
    [
        ('<transform name="to_world"><translate x="nan"/></transform>', "its to_world holds a non-finite number"),
        ('<transform name="to_world"><rotate x="1" angle="inf"/></transform>', "its to_world holds a non-finite"),
        ('<point name="center" x="1" y="inf" z="0"/>', r"its center holds a non-finite number \(NaN or inf\) \(\[1"),
        (
            '<transform name="to_world"><translate x="1e30"/></transform>',
            r"its to_world places it at \[1e\+30, 0.0, 0.0\] m, beyond",
        ),
    ],
)
def test_a_shape_placed_by_a_non_finite_or_far_number_is_refused(tmp_path, place, message):
    """Mitsuba dropped a shape whose to_world or centre held a NaN or inf without a word (the scan missed it), and a
    shape at 1e30 m moved the scene's local origin so far that the sensor's pose was the one refused."""
    text = scene_xml(f'<shape type="sphere" id="ball">{place}</shape>')
    with pytest.raises(SceneError, match=rf"scene\.xml: shape 'ball': {message}"):
        mi_lidar.load_scene(write(tmp_path, text))


@pytest.mark.parametrize("extent", ["0", "-1", "nan", "inf"])
def test_ellipsoids_without_a_finite_positive_extent_are_refused(tmp_path, extent):
    """extent 0, NaN or inf hid every ellipsoid of the set, -1 kept them, silently."""
    from mi_lidar.scene.files import write_ellipsoids_ply

    write_ellipsoids_ply(tmp_path / "e.ply", np.array([[5.0, 0, 0]]), np.full((1, 3), 0.2), np.array([[0, 0, 0, 1.0]]))
    body = (
        '<shape type="ellipsoids" id="bush"><string name="filename" value="e.ply"/>'
        f'<float name="extent" value="{extent}"/></shape>'
    )
    with pytest.raises(SceneError, match=rf"shape 'bush': extent={extent}; the ellipsoids' extent is how many sigmas"):
        mi_lidar.simulate(mi_lidar.load_scene(write(tmp_path, scene_xml(body))), "planar-180")


@pytest.mark.parametrize(
    "typed, shown",
    [
        ('&lt;float name="p_hit" value="0.3"/>', r"""'<float name="p_hit" value="0.3"/>'"""),
        ('>float name="p_hit" value="0.3"/>', r"""'>float name="p_hit" value="0.3"/>'"""),
        ('float name="p_hit" value="0.3"/>', r"""'float name="p_hit" value="0.3"/>'"""),
        ('x<float name="p_hit" value="0.3"/>', "'x'"),
        ('<float name="p_hit" value="0.3"/>\n   oops', "'oops'"),
        ('<![CDATA[1]]><float name="p_hit" value="0.3"/>', "'1'"),
    ],
)
def test_stray_text_in_a_scene_is_refused_naming_the_line_and_the_text(tmp_path, typed, shown):
    """Mitsuba's parser skips text between elements without a word: a property whose '<' was lost or escaped was
    dropped (the material kept p_hit 1), other stray text loaded as if absent."""
    body = f'<shape type="sphere">\n<bsdf type="lidar_material">{typed}</bsdf>\n</shape>'
    with pytest.raises(SceneError) as error:
        mi_lidar.load_scene(write(tmp_path, scene_xml(body)))
    message = str(error.value)
    line = 2 if "oops" not in typed else 3
    assert re.match(rf"{re.escape(str(tmp_path / 'scene.xml'))}: line {line}, column \d+: stray text ", message), (
        message
    )
    assert f'{shown} in <bsdf type="lidar_material">' in message, message
    assert "remove the text, or restore the element's '<'" in message, message


@pytest.mark.parametrize("before, after", [("junk", ""), ("", "\ntrailing words")])
def test_text_outside_the_scene_element_is_refused(tmp_path, before, after):
    """Mitsuba's parser loaded a file with words before or after its <scene> element, ignoring them."""
    with pytest.raises(
        SceneError, match=r"scene\.xml: line \d+, column \d+: text outside the root element '(junk|trail)"
    ):
        mi_lidar.load_scene(write(tmp_path, before + scene_xml("") + after))


def test_whitespace_comments_and_instructions_between_elements_still_load(tmp_path):
    body = '\n\t<!-- a comment: text -->\n  <?note not text?>\n<shape type="sphere">\r\n</shape>  \n'
    scene = mi_lidar.load_scene(write(tmp_path, '<?xml version="1.0"?>\n<!-- head -->\n' + scene_xml(body) + "\n"))
    assert len(scene.shapes()) == 1
