"""The command line as a user runs it: render, simulate, --version, errors."""

import numpy as np
import pytest
from typer.testing import CliRunner

from mi_lidar.cli import app
from mi_lidar.core.log import Log
from mi_lidar.io import read_exr, read_ply

from .conftest import SCENES
from .terminal import assert_whole, invoke_at_80

runner = CliRunner()


def test_version_lists_every_component():
    result = runner.invoke(app, ["--version"])
    assert result.exit_code == 0
    for name in ("mi-lidar", "Mitsuba", "Dr.Jit", "variant", "LLVM"):
        assert name in result.stdout
    assert "llvm_ad_rgb" in result.stdout


def test_render_writes_every_output(tmp_path):
    result = runner.invoke(app, ["render", str(SCENES / "indoor_planar.xml"), "--out", str(tmp_path), "--seed", "2"])
    assert result.exit_code == 0, result.stdout
    assert "returns" in result.stdout
    channels = read_exr(tmp_path / "scan.exr")
    assert {"range", "hit", "element_id", "shape_id", "label", "cos_incidence", "nominal_range", "segments"} <= set(
        channels
    )
    assert channels["range"].shape == (360, 1) and channels["range"].dtype == np.float32
    points, attributes = read_ply(tmp_path / "points.ply")
    assert len(points) == int(channels["hit"].sum())
    np.testing.assert_allclose(np.linalg.norm(points - [0, 0, 0.5], axis=1), attributes["range"], rtol=1e-5)
    for name in ("range.png", "birds_eye.png", "scan.bin"):
        assert (tmp_path / name).stat().st_size > 1000
    assert Log.load(tmp_path / "scan.npz").shape == (1, 360, 1)


def test_render_pattern_override(tmp_path):
    result = runner.invoke(
        app, ["render", str(SCENES / "urban_street.xml"), "--out", str(tmp_path), "--pattern", "hdl32e"]
    )
    assert result.exit_code == 0, result.stdout
    assert read_exr(tmp_path / "scan.exr")["range"].shape[0] == 32


def test_simulate_writes_a_log_per_pose(tmp_path):
    poses = np.stack([np.eye(4)] * 3)
    poses[:, 0, 3] = [0.0, 1.0, 2.0]
    poses[:, 2, 3] = 0.5
    np.save(tmp_path / "poses.npy", poses)
    out = tmp_path / "room.npz"
    result = runner.invoke(
        app, ["simulate", str(SCENES / "indoor_planar.xml"), "--poses", str(tmp_path / "poses.npy"), "--out", str(out)]
    )
    assert result.exit_code == 0, result.stdout
    log = Log.load(out)
    assert log.shape == (3, 360, 1)
    forward = int(np.argmax(log.directions[0, :, 0, 0]))
    # Walking towards the east wall (x = 5 m): 5, 4, 3 m within the 1 cm noise.
    np.testing.assert_allclose(log.ranges[:, forward, 0], [5.0, 4.0, 3.0], atol=0.05)


def room_poses(tmp_path, count: int):
    """``count`` poses of the room's scanner (0.5 m high) along x, as a KITTI file."""
    lines = [f"1 0 0 {0.5 * k} 0 1 0 0 0 0 1 0.5" for k in range(count)]
    (tmp_path / "poses.txt").write_text("\n".join(lines) + "\n")
    return str(tmp_path / "poses.txt")


@pytest.mark.parametrize(
    "name, poses, message",
    [
        ("x.ply", 2, "cannot write 2 scan(s) as '.ply'; use .npz or .bag (a ROS 2 bag folder)"),
        ("x", 2, "cannot write 2 scan(s) as 'no extension'"),
        ("x.txt", 1, "use .npz or .bag (a ROS 2 bag folder); one scan also .ply, .pcd, .bin, .las, .exr"),
        ("x.png", 1, "as '.png'"),
    ],
)
def test_simulate_refuses_an_extension_it_cannot_write(tmp_path, name, poses, message):
    """It wrote an .npz archive under any name (x.ply, x)."""
    out = tmp_path / "out" / name
    result = runner.invoke(
        app,
        ["simulate", str(SCENES / "indoor_planar.xml"), "--poses", room_poses(tmp_path, poses)] + ["--out", str(out)],
    )
    assert result.exit_code == 2 and message in " ".join(result.stdout.split()), result.stdout
    assert not out.parent.exists()


def test_simulate_writes_the_format_the_extension_names(tmp_path):
    out = tmp_path / "scan.ply"
    result = runner.invoke(
        app, ["simulate", str(SCENES / "indoor_planar.xml"), "--poses", room_poses(tmp_path, 1)] + ["--out", str(out)]
    )
    assert result.exit_code == 0, result.stdout
    points, attributes = read_ply(out)
    assert out.read_bytes().startswith(b"ply") and 300 < len(points) <= 360 and "intensity" in attributes


def test_simulate_adds_the_effect_the_scene_lacks(tmp_path):
    def run(*extra):
        out = tmp_path / f"room{len(extra)}.npz"
        command = ["simulate", str(SCENES / "indoor_planar.xml"), "--poses", room_poses(tmp_path, 3), "--out", str(out)]
        assert runner.invoke(app, [*command, *extra]).exit_code == 0
        return Log.load(out)

    plain, dropped = run(), run("--effect", "incidence_dropout(gamma=2)", "--seed", "1")
    assert (
        dropped.sensor["effects"] == ["incidence_dropout(law=cos, mode=stop, gamma=2)"] and dropped.sensor["seed"] == 1
    )
    assert plain.sensor["effects"] == [] and dropped.hit.mean() < plain.hit.mean() - 0.1
    bad = runner.invoke(
        app,
        ["simulate", str(SCENES / "indoor_planar.xml"), "--poses", str(tmp_path / "poses.txt")]
        + ["--out", str(tmp_path / "x.npz"), "--effect", "no_such_effect(a=1)"],
    )
    assert bad.exit_code == 2 and "no_such_effect" in bad.stdout


def test_simulate_rejects_non_rigid_pose_file(tmp_path):
    (tmp_path / "poses.txt").write_text(
        " ".join(["2"] + ["0"] * 4 + ["1"] + ["0"] * 4 + ["1"] + ["0"] * 4 + ["1"]) + "\n"
    )
    result = runner.invoke(
        app,
        [
            "simulate",
            str(SCENES / "indoor_planar.xml"),
            "--poses",
            str(tmp_path / "poses.txt"),
            "--out",
            str(tmp_path / "x.npz"),
        ],
    )
    assert result.exit_code == 2
    assert "not a rigid transform" in " ".join(result.stdout.split())
    assert not (tmp_path / "x.npz").exists()


def test_render_malformed_scene_is_a_clean_error(tmp_path):
    bad = tmp_path / "bad.xml"
    bad.write_text("<scene version='3.0.0'><shape type='sphere'>")
    result = runner.invoke(app, ["render", str(bad), "--out", str(tmp_path / "o")])
    assert result.exit_code == 2
    assert "bad.xml" in " ".join(result.stdout.split())


def test_info_and_convert_on_a_simulated_log(tmp_path):
    log_path = tmp_path / "room.npz"
    runner.invoke(app, ["render", str(SCENES / "indoor_planar.xml"), "--out", str(tmp_path)])
    (tmp_path / "scan.npz").rename(log_path)
    result = runner.invoke(app, ["info", str(log_path)])
    assert result.exit_code == 0, result.stdout
    assert "1 x 360 x 1" in result.stdout
    result = runner.invoke(app, ["convert", str(log_path), str(tmp_path / "room.pcd")])
    assert result.exit_code == 0, result.stdout
    assert (tmp_path / "room.pcd").stat().st_size > 1000


def test_primitives_list_prints_one_table_that_fits_80_columns(tmp_path):
    """The library's primitives once, on stdout, in 80 columns: whole ids, extents and returns counts."""
    from mi_lidar.hybrid.classes import CLASS_ID
    from mi_lidar.hybrid.model import EllipsoidSet
    from mi_lidar.hybrid.primitives import Primitive, PrimitiveLibrary

    label = CLASS_ID["medium_shrub"]
    means = np.array([[0.0, 0.0, 0.0], [0.5, 0.2, 1.0]])
    ellipsoids = EllipsoidSet(means, np.tile(np.eye(3) * 0.04, (2, 1, 1)), np.full(2, 0.6), label=label)
    PrimitiveLibrary(
        [
            Primitive(
                f"train_medium_shrub_{segment}",
                label,
                ellipsoids,
                means.min(0) - 1.0,
                means.max(0) + 1.0,
                {"scene": "train", "segment": segment, "patch": segment > 1000, "n_points": n},
            )
            for segment, n in ((6, 935), (1001007, 1200))
        ]
    ).save(tmp_path / "lib")
    result = invoke_at_80(["primitives", "list", tmp_path / "lib"])
    assert result.exit_code == 0, result.output
    assert_whole(
        result.stdout, "train_medium_shrub_6", "train_medium_shrub_1001007", "2.50\u00d72.20\u00d73.00", "935", "1,200*"
    )
    assert result.output.count("train_medium_shrub_1001007") == 1  # one table, not one on stderr and one on stdout


def test_fit_scene_annotate_and_compose_name_every_file_they_write(tmp_path):
    """They wrote a ground PLY, a pattern table, PLY assets and two PNG previews and named only the JSON or XML
    (fit-scene: only the XML and the previews, not its assets folder)."""

    def files():
        return {p for p in tmp_path.rglob("*") if p.is_file()}

    def run_and_name(*args):
        before = files()
        result = invoke_at_80(args)
        assert result.exit_code == 0, result.output
        said = "".join((result.stdout + result.stderr).split())  # a long path may wrap anywhere at 80 columns
        written = files() - before
        assert written and all(f"wrote{p}" in said for p in written), (sorted(written), said)
        return {p.name for p in written}

    log = tmp_path / "world.npz"
    assert invoke_at_80(["synth-world", "--out", log, "--seed", 11, "--length", 20, "--width", 20]).exit_code == 0
    fitted = run_and_name("fit-scene", log, "--out", tmp_path / "fitted")
    assert {"scene.xml", "pattern.npy", "scene_range.png", "scene_top.png"} < fitted
    assert any(n.startswith("ground_b") for n in fitted)  # in fitted/scene_assets/, named with its folder
    assert invoke_at_80(["primitives", "extract", log, "--library", tmp_path / "lib"]).exit_code == 0
    assert run_and_name("annotate", log, "--out", tmp_path / "a.json") == {"a.json", "a_ground.ply", "a_pattern.npy"}
    composed = run_and_name("compose", tmp_path / "a.json", "--library", tmp_path / "lib", "--out", tmp_path / "c.xml")
    assert {"c.xml", "c_range.png", "c_top.png"} < composed and any(n.endswith(".ply") for n in composed)


@pytest.mark.slow
def test_hybrid_scene_flow_from_the_command_line(tmp_path):
    import mitsuba as mi

    import mi_lidar

    def run(*args):
        result = runner.invoke(app, [str(a) for a in args])
        assert result.exit_code == 0, result.stdout
        return result

    run("synth-world", "--out", tmp_path / "train.npz", "--seed", 11, "--length", 40, "--width", 30)
    run("synth-world", "--out", tmp_path / "test.npz", "--seed", 22, "--length", 40, "--width", 30)
    fitted = run("fit-scene", tmp_path / "train.npz", "--out", tmp_path / "fitted")
    said = "".join((fitted.stdout + fitted.stderr).split())
    assert "scene_range.png" in said and "scene_top.png" in said and "planar" not in said  # a 3D log, previews named
    extracted = run("primitives", "extract", tmp_path / "train.npz", "--library", tmp_path / "lib")
    said = "".join((extracted.stdout + extracted.stderr).split())  # the path may wrap the line anywhere
    assert said.count("primitives") == 1 and "lib:" in said, said  # it said so twice, in two wordings
    assert "shrub" in run("primitives", "list", tmp_path / "lib").stdout
    run("annotate", tmp_path / "test.npz", "--out", tmp_path / "ann.json")
    run("compose", tmp_path / "ann.json", "--library", tmp_path / "lib", "--out", tmp_path / "composed.xml")
    for xml in (tmp_path / "fitted" / "scene.xml", tmp_path / "composed.xml"):
        image = np.asarray(mi.render(mi_lidar.load_scene(xml)))
        assert np.mean(image[..., 1]) > 0.2  # the scene returns beams


def test_the_scan_summary_keeps_each_label_beside_its_count():
    """'returns per label' wrapped between a label and its count ('5:' at a line's end, '9,894' on the next)."""
    from rich.console import Console

    from mi_lidar.cli.render import scan_summary

    rng = np.random.default_rng(0)
    shape = (1, 16, 2000)
    directions = np.broadcast_to(np.array([1.0, 0.0, 0.0]), (*shape, 3)).copy()
    log = Log(
        poses=np.eye(4)[None],
        directions=directions,
        ranges=np.full(shape, 5.0),
        hit=np.ones(shape, bool),
        times=np.zeros(shape),
        attributes={"label": rng.integers(1, 10, shape).astype(np.int32)},
    )
    console = Console(width=60, record=True)
    console.print(scan_summary(log, "labels"))
    rows = console.export_text().splitlines()
    start = next(i for i, row in enumerate(rows) if "returns per label" in row)
    cells = [row.split("│")[2].strip() for row in rows[start:] if row.count("│") >= 3][:6]
    assert len(cells) > 1, cells  # the row wraps at this width ...
    assert not any(cell.endswith(":") for cell in cells), cells  # ... but never between a label and its count


def test_the_scan_summary_gives_a_small_log_its_rate_in_rays():
    """A planar room's 2,880 rays in 0.12 s read '(0.0 M rays/s)'; large logs keep millions."""
    from rich.console import Console

    from mi_lidar.cli.render import ray_rate, scan_summary

    shape = (8, 360, 1)
    log = Log(
        poses=np.tile(np.eye(4), (8, 1, 1)),
        directions=np.broadcast_to(np.array([1.0, 0.0, 0.0]), (*shape, 3)).copy(),
        ranges=np.full(shape, 5.0),
        hit=np.ones(shape, bool),
        times=np.zeros(shape),
    )
    console = Console(width=80, record=True)
    console.print(scan_summary(log, "room", elapsed=0.12))
    assert "0.12 (24,000 rays/s)" in console.export_text()
    assert ray_rate(28_928, 0.017) == "1.7 M rays/s"
    assert ray_rate(10_000, 0.1) == "0.1 M rays/s"
