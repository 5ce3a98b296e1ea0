"""Dataset specs: YAML and TOML read the same, bad fields are named, frames map to scenes; nuScenes rigs."""

import numpy as np
import pytest

from mi_lidar.core.errors import SpecError
from mi_lidar.dataset.spec import load_spec
from tests.conftest import SCENES

YAML = f"""
seed: 1
rig:
  lidars: [{{pattern: vlp16}}]
  cameras: [{{name: front, mount: {{xyz: [1, 0, 1.5], rpy_deg: [0, 10, 0]}}}}]
scenes:
  - {{name: a, xml: {SCENES / "urban_street.xml"}, frames: 3, trajectory: {{waypoints: [[0, 0], [10, 0]]}}}}
  - name: b
    random: {{classes: [rock]}}
    library: lib
    variants: 3
    frames: 7
    trajectory: {{waypoints: [[0, 0], [10, 0]]}}
"""
TOML = f"""
seed = 1
[rig]
lidars = [{{pattern = "vlp16"}}]
cameras = [{{name = "front", mount = {{xyz = [1, 0, 1.5], rpy_deg = [0, 10, 0]}}}}]
[[scenes]]
name = "a"
xml = "{SCENES / "urban_street.xml"}"
frames = 3
trajectory = {{waypoints = [[0, 0], [10, 0]]}}
[[scenes]]
name = "b"
random = {{classes = ["rock"]}}
library = "lib"
variants = 3
frames = 7
trajectory = {{waypoints = [[0, 0], [10, 0]]}}
"""


@pytest.fixture
def folder(tmp_path):
    (tmp_path / "lib").mkdir()
    return tmp_path


def test_yaml_and_toml_agree_and_frames_split_into_variants(folder):
    (folder / "s.yaml").write_text(YAML)
    (folder / "s.toml").write_text(TOML)
    spec, same = load_spec(folder / "s.yaml"), load_spec(folder / "s.toml")
    assert spec.model_dump(exclude={"source"}) == same.model_dump(exclude={"source"})
    assert spec.frames == 10
    assert [spec.locate(k) for k in (0, 2, 3, 4, 5, 9)] == [
        (0, 0, 0, 3),
        (0, 0, 2, 3),
        (1, 0, 0, 2),
        (1, 0, 1, 2),
        (1, 1, 0, 3),
        (1, 2, 1, 2),
    ]  # the 7 frames of b split 2 + 3 + 2
    with pytest.raises(SpecError, match="frame 10 out of range"):
        spec.locate(10)


@pytest.mark.parametrize(
    "change, message",
    [
        (("frames: 3", "frames: 0"), r"scenes\.0\.frames: Input should be greater than or equal to 1"),
        (("seed: 1", "seed: 1\nsed: 2"), r"sed: Extra inputs are not permitted"),
        (("library: lib", "library: nowhere"), r"scenes\.1\.library: nowhere"),
        (("variants: 3", "variants: 9"), r"variants \(9\) exceeds frames \(7\)"),
        (("classes: [rock]", "classes: [oak]"), r"unknown class 'oak'"),
        (("    library: lib\n", ""), r"random scenes need library"),
        (("rpy_deg: [0, 10, 0]", "matrix: [[1, 0, 0, 0]]"), r"matrix has 1 rows"),
        (("[[0, 0], [10, 0]]}}", "[[0, 0], [.nan, 0]]}}"), r"scenes\.0\.trajectory\.waypoints\.1\.0: .*finite"),
        (("[[0, 0], [10, 0]]}}", "[[0, 0, 1, 2], [10, 0]]}}"), r"waypoint 0 has 4 numbers; give \[x, y\]"),
        (("xyz: [1, 0, 1.5]", "xyz: [1, .inf, 1.5]"), r"rig\.cameras\.0\.mount\.xyz\.1: .*finite"),
        (("pattern: vlp16", "pattern: vlp17"), r"rig\.lidars\.0\.pattern: unknown firing pattern 'vlp17'"),
        (("pattern: vlp16", "pattern: beams.csv"), r"rig\.lidars\.0\.pattern: beams\.csv"),  # relative to the spec
        (("pattern: vlp16", "pattern: vlp16, effects: 'range_nois(k=1)'"), r"rig\.lidars\.0\.effects: .*'range_nois'"),
        (("pattern: vlp16", "pattern: vlp16, density: 'gaussian(sigm=1)'"), r"rig\.lidars\.0\.density: .*sigm"),
        (("pattern: vlp16", "pattern: vlp16, max_range: 0.2"), r"rig\.lidars\.0: sensor model: max_range=0\.2"),
        # read and rendered: a range window reaching 1e30 m, returns spread by a range noise of 1e30 m
        (("pattern: vlp16", "pattern: vlp16, max_range: 1e30"), r"lidars\.0\.max_range: Input should be less than or"),
        (("pattern: vlp16", "pattern: vlp16, range_sigma: 1e30"), r"lidars\.0\.range_sigma: Input should be less than"),
        # read, then rendered for ever (10**12 frames), garbage (a rotation of 1e30 degrees, an empty or spaced
        # KITTI object type, a 16-bit id of 2**40), or failed in every frame, each retried (a waypoint 1e30 m away)
        (("frames: 3", "frames: 1000000000000"), r"scenes\.0\.frames: Input should be less than or equal to 1000000"),
        (("frames: 7", "frames: 999999"), r"frames add up to 1,000,002; KITTI names frames with 6 digits"),
        (("[[0, 0], [10, 0]]}}", "[[0, 0], [1e30, 0]]}}"), r"waypoints\.1\.0: Input should be less than or equal to"),
        (
            ("rpy_deg: [0, 10, 0]", "rpy_deg: [0, 10, 1e30]"),
            r"mount\.rpy_deg\.2: Input should be less than or equal to",
        ),
        (("xyz: [1, 0, 1.5]", "xyz: [-1e30, 0, 1.5]"), r"mount\.xyz\.0: Input should be greater than or equal to"),
        (("{name: front,", "{name: front, width: 100000,"), r"cameras\.0\.width: Input should be less than or equal"),
        (("seed: 1", "seed: 1\noutput: {spp: 1000000000}"), r"output\.spp: Input should be less than or equal to 4096"),
        (("seed: 1", "seed: 1\noutput: {semantic_ids: {road: -1}}"), r"semantic_ids\.road: Input should be greater"),
        (("seed: 1", "seed: 1\noutput: {semantic_ids: {road: 65536}}"), r"semantic_ids\.road: Input should be less"),
    ],
)
def test_bad_specs_name_the_field(folder, change, message):
    (folder / "s.yaml").write_text(YAML.replace(*change))
    with pytest.raises(SpecError, match=message):
        load_spec(folder / "s.yaml")


HEADER = """# A forest from a library made first, from the repository root:
#   mi-lidar synth-world --out out/world.npz --seed 11
#   mi-lidar primitives extract out/world.npz --library out/library
#   mi-lidar dataset specs/s.yaml --out out/forest
"""


def test_a_missing_library_is_named_with_the_commands_of_the_spec_header(tmp_path):
    (tmp_path / "specs").mkdir()
    spec = tmp_path / "specs" / "s.yaml"
    spec.write_text(HEADER + YAML.replace("library: lib", "library: ../out/library"))
    with pytest.raises(SpecError) as raised:
        load_spec(spec)
    message = str(raised.value)
    assert f"scenes.1.library: ../out/library ({tmp_path / 'out' / 'library'}), the primitive library of scene 'b'" in (
        message
    )
    assert message.endswith(
        "The spec's header says: A forest from a library made first, from the repository root:\n"
        "  mi-lidar synth-world --out out/world.npz --seed 11\n"
        "  mi-lidar primitives extract out/world.npz --library out/library"
    ), message  # the spec's own `mi-lidar dataset` line is not a step to make the library


def test_a_missing_library_without_a_header_names_the_verb_that_makes_one(folder):
    (folder / "s.yaml").write_text(YAML.replace("library: lib", "library: nowhere"))
    with pytest.raises(SpecError) as raised:
        load_spec(folder / "s.yaml")
    assert str(raised.value).endswith(
        f"Make a primitive library with `mi-lidar primitives extract LOG --library {folder / 'nowhere'}`."
    )


def test_a_missing_density_file_is_named_with_its_entry_its_folder_and_the_verb_that_fits_one(tmp_path):
    """It was 'rig.lidars.0.density/effects: /abs/path: no such density file': neither the path as written
    nor the folder it is taken from."""
    (tmp_path / "specs").mkdir()
    spec = tmp_path / "specs" / "s.yaml"
    spec.write_text(YAML.replace("{pattern: vlp16}", "{name: top, density: 'np_reg(file=models/sensor.npz)'}"))
    (tmp_path / "specs" / "lib").mkdir()
    with pytest.raises(SpecError) as raised:
        load_spec(spec)
    resolved = tmp_path / "specs" / "models" / "sensor.npz"
    assert str(raised.value) == (
        f"{spec}: referenced files do not exist (paths in a spec are relative to its folder, {tmp_path / 'specs'}):\n"
        f"  rig.lidars.0.density: models/sensor.npz ({resolved}), the density file of Lidar 'top'\n"
        f"Fit a density file with `mi-lidar fit-sensor LOG SCENE.xml --out {resolved}`."
    )


def test_a_pattern_table_is_read_from_the_spec_folder(folder, monkeypatch):
    from mi_lidar.core.patterns import get_pattern, to_table
    from mi_lidar.dataset.rig import build_rig

    to_table(get_pattern("vlp16"), folder / "beams.csv")
    (folder / "s.yaml").write_text(YAML.replace("pattern: vlp16", "pattern: beams.csv"))
    monkeypatch.chdir(folder / "lib")  # not the spec's folder
    pattern = build_rig(load_spec(folder / "s.yaml")).lidars[0].pattern
    assert np.allclose(pattern.elevation, get_pattern("vlp16").elevation, rtol=0, atol=1e-15)  # CSV round trip


@pytest.mark.parametrize("name", ["", "Traffic Sign"])
def test_an_object_class_that_is_not_one_word_is_refused(folder, name):
    """It went to the first column of label_2 lines as it was: empty, or two columns for one."""
    objects = f"frames: 3, objects: [{{class: '{name}', shapes: [car_body]}}],"
    (folder / "s.yaml").write_text(YAML.replace("frames: 3,", objects))
    with pytest.raises(SpecError, match=r"scenes\.0\.objects\.0\.class: String should match pattern"):
        load_spec(folder / "s.yaml")


def test_an_unreadable_nuscenes_file_is_refused_before_any_frame(folder):
    """Read per frame, it failed every frame (each retried) and the run exited 1 saying to run it again."""
    (folder / "info.pkl").write_bytes(b"not a pickle")
    text = YAML.replace("rig:\n", "rig:\n  nuscenes: {file: info.pkl, cameras: [CAM_FRONT]}\n")
    (folder / "s.yaml").write_text(text)
    with pytest.raises(SpecError, match=r"the rig cannot be built:\n  rig\.nuscenes: .*info\.pkl: not a nuScenes info"):
        load_spec(folder / "s.yaml")


@pytest.mark.parametrize("address", ["nope:xx", "host:", ":99999"])
def test_a_dashboard_address_without_a_port_is_refused_before_the_cluster(tmp_path, address):
    """Dask's 'Cluster failed to start: invalid literal for int() with base 10' came as a traceback."""
    from mi_lidar.dataset.run import run_dataset

    (tmp_path / "lib").mkdir()
    (tmp_path / "s.yaml").write_text(YAML)
    with pytest.raises(SpecError, match=rf"dashboard address '{address}': .* needs a port number from 0 to 65535"):
        run_dataset(load_spec(tmp_path / "s.yaml"), tmp_path / "out", dashboard_address=address)
    assert not (tmp_path / "out").exists()


def test_unreadable_specs(folder):
    with pytest.raises(SpecError, match="no such spec file"):
        load_spec(folder / "missing.yaml")
    (folder / "s.json").write_text("{}")
    with pytest.raises(SpecError, match="write the spec as .yaml"):
        load_spec(folder / "s.json")
    (folder / "s.yaml").write_text("- a list")
    with pytest.raises(SpecError, match="must be a mapping"):
        load_spec(folder / "s.yaml")


def test_nuscenes_rig_reproduces_the_recorded_calibration(folder, shared_data):
    """Reference camera CAM_FRONT and nuScenes' lidar2ego: Tr_velo_to_cam matches the file's lidar2cam,
    and P2 / P3 carry the file's cam2img scaled to the images (principal points 16-42 px off centre at
    full size), shifted by half a pixel to image-corner coordinates.

    The recorded lidar2cam goes through the global frame at the two sensors' timestamps (35 ms apart, the
    car at about 9 m/s), so it differs from the rig's static transform by the ego motion: rotations to
    2e-3, translations to 0.35 m (0.33 m along the optical axis).
    """
    from mi_lidar.dataset.rig import build_rig
    from mi_lidar.io.nuscenes import _NumpyOnly

    info = next((shared_data / "nuscenes").glob("*.pkl"))
    text = YAML.replace("  cameras: [{name: front, mount: {xyz: [1, 0, 1.5], rpy_deg: [0, 10, 0]}}]\n", "")
    rig = f"rig:\n  nuscenes: {{file: {info}, cameras: [CAM_FRONT, CAM_BACK], image_scale: 0.25}}\n"
    text = text.replace("rig:\n", rig)
    (folder / "s.yaml").write_text(text)
    rig = build_rig(load_spec(folder / "s.yaml"))
    assert [(c.name, c.width, c.height) for c in rig.cameras] == [("CAM_FRONT", 400, 225), ("CAM_BACK", 400, 225)]
    assert rig.cameras[0].fov_deg == pytest.approx(64.56, abs=0.01)  # 2 atan(800 / 1266.4)
    with open(info, "rb") as stream:
        images = _NumpyOnly(stream).load()["data_list"][0]["images"]
    recorded = np.asarray(images["CAM_FRONT"]["lidar2cam"])
    calibration = rig.calibration()
    transform = calibration["Tr_velo_to_cam"]
    np.testing.assert_allclose(transform[:, :3], recorded[:3, :3], atol=2e-3)
    assert np.linalg.norm(transform[:, 3] - recorded[:3, 3]) < 0.35
    for name, intrinsics in (("CAM_FRONT", calibration["P2"][:, :3]), ("CAM_BACK", rig.cameras[1].intrinsics)):
        k = np.asarray(images[name]["cam2img"])[:3, :3]
        np.testing.assert_allclose(intrinsics[:2, 2], (k[:2, 2] + 0.5) * 0.25, atol=1e-9)
        np.testing.assert_allclose(intrinsics[0, 0], k[0, 0] * 0.25, rtol=1e-9)
