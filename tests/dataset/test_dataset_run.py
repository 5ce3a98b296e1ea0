"""A 4-frame camera + Lidar dataset: serial run, a run killed by SIGKILL, resumed on a 2-worker LocalCluster.

Checks the KITTI / SemanticKITTI layout, that labelled points of the parked car fall inside its 3D box
and its 2D box through the written calibration, that the resumed run kept the killed run's finished
frames untouched and left no partial file, and that every frame's digests equal the serial run's.
"""

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from mi_lidar.core.errors import SceneError, SpecError
from mi_lidar.dataset import load_spec, run_dataset
from mi_lidar.dataset.workers import host_cores, worker_threads, workers_per_host
from mi_lidar.io.kitti import read_kitti_bin
from mi_lidar.io.kitti_labels import read_kitti_calib, read_kitti_labels, read_semantic_labels
from tests.conftest import SCENES
from tests.hybrid.libraries import small_library

SPEC = """
name: ci-dataset
seed: 5
rig:
  lidars:
    - name: top
      pattern: vlp16
      mount: {{xyz: [0, 0, 1.8]}}
      effects: "range_noise(sigma0=0.01), outliers(p_near=0.01, p_uniform=0.01, uniform_max=60)"
  cameras:
    - {{name: front, width: 128, height: 80, fov_deg: 80, mount: {{xyz: [0.5, 0, 1.6]}}}}
    - {{name: left, width: 96, height: 64, fov_deg: 90, mount: {{xyz: [0, 0.3, 1.6], rpy_deg: [0, 0, 90]}}}}
scenes:
  - name: street
    xml: {street}
    frames: 2
    labels: {{1: road, 2: building, 3: pole, 4: car, 6: vegetation}}
    objects:
      - {{class: Car, shapes: [car_body, car_cabin]}}
      - {{class: Pole, shapes: [pole_a]}}
    trajectory: {{waypoints: [[-6, 0], [4, 0]]}}
  - name: forest
    random: {{classes: [small_tree, rock], count: 10, lateral: [3, 10]}}
    library: library
    variants: 2
    frames: 2
    trajectory: {{waypoints: [[0, 0], [20, 2]]}}
output: {{spp: 2, overlays: true}}
"""


@pytest.fixture(scope="module")
def spec_path(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("spec")
    small_library(folder / "library")
    path = folder / "dataset.yaml"
    path.write_text(SPEC.format(street=SCENES / "urban_street.xml"))
    return path


@pytest.fixture(scope="module")
def serial(spec_path, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("serial")
    report = run_dataset(load_spec(spec_path), out, serial=True)
    assert report.rendered == 4 and not report.failed
    return out


def frames_of(out: Path) -> dict:
    return json.loads((out / "manifest.json").read_text())["frames"]


@pytest.fixture(scope="module")
def resumed(spec_path, tmp_path_factory):
    """A serial CLI run killed by SIGKILL after its first frame, then resumed on a 2-worker LocalCluster."""
    out = tmp_path_factory.mktemp("resumed")
    command = [str(Path(sys.executable).parent / "mi-lidar"), "dataset", str(spec_path), "--out", str(out), "--serial"]
    process = subprocess.Popen(command, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    manifest = out / "manifest.json"
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and process.poll() is None:
        if manifest.is_file() and frames_of(out):
            break
        time.sleep(0.02)
    os.killpg(process.pid, signal.SIGKILL)
    process.wait()
    before = frames_of(out)
    kept = {name: (out / name).stat().st_mtime_ns for record in before.values() for name in record["files"]}
    from distributed import Client

    waited, wait = [], Client.wait_for_workers

    def spy(self, n_workers, *args, **kwargs):
        waited.append(n_workers)
        return wait(self, n_workers, *args, **kwargs)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(Client, "wait_for_workers", spy)
        report = run_dataset(load_spec(spec_path), out, workers=2, dashboard_address=None)
    assert waited == [2], "the run must wait for both workers before counting them per host"
    return out, before, kept, report


def test_resume_keeps_finished_frames_and_cluster_equals_serial(resumed, serial):
    out, before, kept, report = resumed
    assert 1 <= len(before) < 4, f"the kill should land mid-run; {len(before)} frames were done"
    assert report.skipped == len(before) and report.rendered == 4 - len(before) and not report.failed
    assert all((out / name).stat().st_mtime_ns == mtime for name, mtime in kept.items()), "a finished frame was redone"
    assert not [p for p in out.rglob(".*") if ".tmp" in p.name], "partial files left behind"
    assert len(report.worker_peak_mib) == 2
    # two workers share the cores: each runs Dr.Jit on cores // 2 threads (1 on this 2-core machine)
    assert [s["threads"] for s in report.worker_setup.values()] == [max(1, host_cores() // 2)] * 2
    cluster, reference = frames_of(out), frames_of(serial)
    assert sorted(cluster) == ["0", "1", "2", "3"]
    for k in reference:
        assert cluster[k]["files"] == reference[k]["files"], f"frame {k} differs from the serial run"


def test_kitti_layout(serial):
    names = sorted(str(p.relative_to(serial)) for p in serial.rglob("*") if p.is_file())
    for k in range(4):
        for pattern in ("velodyne/{:06d}.bin", "labels/{:06d}.label", "calib/{:06d}.txt", "label_2/{:06d}.txt"):
            assert pattern.format(k) in names
        assert f"image_2/{k:06d}.png" in names and f"image_3/{k:06d}.png" in names
        assert f"overlay/{k:06d}_front.png" in names
    poses = np.loadtxt(serial / "poses.txt")
    assert poses.shape == (4, 12)
    from PIL import Image

    assert Image.open(serial / "image_2" / "000000.png").size == (128, 80)
    assert Image.open(serial / "image_3" / "000000.png").size == (96, 64)
    manifest = json.loads((serial / "manifest.json").read_text())
    assert manifest["spec_digest"] and manifest["versions"]["mitsuba"] and "intensity" in manifest["notes"][0]


def test_points_and_labels(serial):
    for k in range(4):
        points = read_kitti_bin(serial / "velodyne" / f"{k:06d}.bin")
        semantic, instance = read_semantic_labels(serial / "labels" / f"{k:06d}.label")
        assert len(points) == len(semantic) > 1000
        intensity = points[:, 3]  # the simulated intensity: non-negative integers that vary over the scene
        assert np.all(intensity >= 0) and np.all(intensity == np.round(intensity)) and np.std(intensity) > 1.0
        # outliers are returns of no element: unlabeled (0), no instance
        assert 0 < np.count_nonzero(semantic == 0) < 0.05 * len(semantic) and np.all(instance[semantic == 0] == 0)
        if k < 2:  # street: road (40) and buildings (50) everywhere, the car (10) has instance 1
            assert {40, 50} <= set(np.unique(semantic).tolist())
            assert np.all(semantic[instance == 1] == 10)
        else:  # forest: ground (101), object points carry instances
            assert 101 in semantic and np.all(instance[semantic == 101] == 0)
            assert set(np.unique(semantic[instance > 0]).tolist()) <= {103, 108}


def test_car_points_fall_in_its_3d_and_2d_boxes(serial):
    """Calibration consistency: the car's labelled points land in its label_2 3D box and 2D box."""
    frame = frames_of(serial)["0"]
    objects = read_kitti_labels(serial / "label_2" / "000000.txt")
    row = objects[[o["instance"] for o in frame["objects"]].index(1)]
    assert row["type"] == "Car" and row["truncated"] == 0.0 and row["occluded"] == 0  # in plain view
    calib = read_kitti_calib(serial / "calib" / "000000.txt")
    points = read_kitti_bin(serial / "velodyne" / "000000.bin")[:, :3]
    _, instance = read_semantic_labels(serial / "labels" / "000000.label")
    car = points[instance == 1]
    assert len(car) > 50
    camera = (calib["R0_rect"] @ calib["Tr_velo_to_cam"] @ np.c_[car, np.ones(len(car))].T).T
    # 3D box: bottom centre (x, y, z), y down, rotation_y about y. Tolerance 10 cm: range noise is
    # 2.2 cm (2 cm sensor sigma and 1 cm range_noise effect), label values are rounded to 1 cm.
    c, s = np.cos(row["rotation_y"]), np.sin(row["rotation_y"])
    local = camera - [row["x"], row["y"], row["z"]]
    along, across = local[:, 0] * c - local[:, 2] * s, local[:, 0] * s + local[:, 2] * c
    assert np.all(np.abs(along) <= row["length"] / 2 + 0.1)
    assert np.all(np.abs(across) <= row["width"] / 2 + 0.1)
    assert np.all((local[:, 1] <= 0.1) & (local[:, 1] >= -row["height"] - 0.1))
    pixels = (calib["P2"] @ np.c_[camera, np.ones(len(camera))].T).T
    uv = pixels[:, :2] / pixels[:, 2:]
    assert np.all((uv[:, 0] >= row["left"] - 1.5) & (uv[:, 0] <= row["right"] + 1.5))  # 10 cm at 10 m: 1 px
    assert np.all((uv[:, 1] >= row["top"] - 1.5) & (uv[:, 1] <= row["bottom"] + 1.5))


def test_other_spec_in_the_same_folder_is_refused(serial, spec_path, tmp_path):
    changed = tmp_path / "changed.yaml"
    changed.write_text(spec_path.read_text().replace("seed: 5", "seed: 6"))
    (tmp_path / "library").symlink_to(spec_path.parent / "library")
    with pytest.raises(SpecError, match="different spec"):
        run_dataset(load_spec(changed), serial, serial=True)


@pytest.mark.parametrize(
    "change, error, message",
    [
        # the forest scene made from an annotation file that is not JSON
        (
            ("random: {classes: [small_tree, rock], count: 10, lateral: [3, 10]}", "annotation: bad.json"),
            SceneError,
            "not JSON",
        ),
        (("3: pole, 4: car, 6: vegetation", "3: pole"), SpecError, r"element labels \[4, 6\] have no class name"),
        (("shapes: [pole_a]", "shapes: [pole_z]"), SpecError, r"object 1 names shapes \['pole_z'\]"),
        (("classes: [small_tree, rock]", "classes: [small_tree, large_tree]"), SpecError, r"no primitive.*large_tree"),
    ],
)
@pytest.mark.parametrize("serial_run", [False, True])
def test_a_scene_that_would_fail_every_frame_stops_the_run_before_any_frame(
    spec_path, tmp_path, monkeypatch, change, error, message, serial_run
):
    """Both scenes are checked first: no cluster starts, not even the good scene's frames are rendered, and the
    output folder the run made is removed again."""
    import mi_lidar.dataset.frame
    import mi_lidar.dataset.run

    def refuse(*args, **kwargs):
        raise AssertionError("a frame was started")

    monkeypatch.setattr(mi_lidar.dataset.run, "_run_on_dask", refuse)
    monkeypatch.setattr(mi_lidar.dataset.frame, "render_frame", refuse)
    changed = tmp_path / "changed.yaml"
    text = spec_path.read_text().replace(*change)
    changed.write_text(text.replace("    variants: 2\n", "") if "annotation:" in text else text)  # one fixed scene
    (tmp_path / "bad.json").write_text('{"format": "mi-lidar-annotation", "objects": [')
    (tmp_path / "library").symlink_to(spec_path.parent / "library")
    with pytest.raises(error, match=message):
        run_dataset(load_spec(changed), tmp_path / "out", serial=serial_run)
    assert not (tmp_path / "out").exists()  # not even the folder: the run made it and wrote nothing


def test_workers_share_their_hosts_cores():
    """A lone worker keeps every core; workers on one host split them; hosts are counted apart."""
    assert worker_threads(2, 1) == 2 and worker_threads(2, 2) == 1 and worker_threads(2, 3) == 1
    assert worker_threads(16, 4) == 4
    addresses = ["tcp://10.0.0.5:40001", "tcp://10.0.0.5:40002", "tcp://10.0.0.6:40001"]
    assert workers_per_host(addresses) == {"10.0.0.5": 2, "10.0.0.6": 1}


@pytest.fixture
def dask_cluster(tmp_path):
    """A real Dask cluster on this machine: ``dask scheduler`` and ``dask worker --nworkers 2 --nthreads 1``."""
    address_file = tmp_path / "scheduler.json"
    dask = str(Path(sys.executable).parent / "dask")
    started = [
        subprocess.Popen(
            [dask, "scheduler", "--scheduler-file", str(address_file), "--port", "0", "--dashboard-address", ":0"],
            start_new_session=True,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
    ]
    try:
        address = None
        while address is None:  # the scheduler writes the file in place: wait until it parses
            assert started[0].poll() is None, "dask scheduler exited"
            time.sleep(0.1)
            with contextlib.suppress(OSError, ValueError, KeyError):  # not written yet, or half written
                address = json.loads(address_file.read_text())["address"]
        started.append(
            subprocess.Popen(
                [dask, "worker", "--scheduler-file", str(address_file), "--nworkers", "2", "--nthreads", "1"],
                start_new_session=True,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
        )
        yield address
    finally:
        for process in reversed(started):
            os.killpg(process.pid, signal.SIGTERM)
            process.wait()


@pytest.mark.slow
def test_an_existing_dask_cluster_renders_the_serial_frames(spec_path, serial, dask_cluster, tmp_path):
    """--scheduler: the frames go to a separately started scheduler and its two workers (one Dr.Jit
    thread each on 2 cores) and come back with the serial run's digests."""
    from distributed import Client

    with Client(dask_cluster) as client:
        client.wait_for_workers(2)
    report = run_dataset(load_spec(spec_path), tmp_path / "out", scheduler=dask_cluster)
    assert report.rendered == 4 and not report.failed and report.dashboard.startswith("http")
    assert [s["threads"] for s in report.worker_setup.values()] == [max(1, host_cores() // 2)] * 2
    assert len({s["pid"] for s in report.worker_setup.values()}) == 2
    cluster, reference = frames_of(tmp_path / "out"), frames_of(serial)
    assert {k: r["files"] for k, r in cluster.items()} == {k: r["files"] for k, r in reference.items()}
