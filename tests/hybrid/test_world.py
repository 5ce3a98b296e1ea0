import numpy as np

from mi_lidar.core.log import Log
from mi_lidar.hybrid.classes import CLASS_ID, GROUND_CLASSES, PATCH_BASE
from mi_lidar.hybrid.true_sensor import SensorSpec, _echo, path_poses, render_log
from mi_lidar.hybrid.world import WorldSpec, make_world

from .conftest import SMALL_WORLD


def test_log_has_labels_for_every_return(small_log):
    s, h, w = small_log.shape
    assert (h, w) == (32, 360)
    label, inst = small_log.attributes["label"], small_log.attributes["instance"]
    assert np.all(label[small_log.hit] > 0)
    assert np.all(label[~small_log.hit] == 0) and np.all(inst[~small_log.hit] == -1)
    seen = set(np.unique(label[small_log.hit]))
    assert CLASS_ID["ground"] in seen and len(seen - set(GROUND_CLASSES)) >= 2
    assert 0.3 < small_log.hit.mean() < 0.95


def test_log_round_trips_through_disk(small_log, tmp_path):
    back = Log.load(small_log.save(tmp_path / "w.npz"))
    np.testing.assert_array_equal(back.attributes["instance"], small_log.attributes["instance"])
    np.testing.assert_array_equal(back.hit, small_log.hit)


def test_seeds_change_layout_and_repeat_exactly():
    a, b, a2 = make_world(1, SMALL_WORLD), make_world(2, SMALL_WORLD), make_world(1, SMALL_WORLD)
    np.testing.assert_array_equal(a.vertices, a2.vertices)
    assert len(a.faces) != len(b.faces) or not np.allclose(a.vertices[:100], b.vertices[:100])


def test_patches_share_one_instance():
    world = make_world(3, WorldSpec(length=60, width=40, n_patches=2, n_grass=0))
    patches = [o for o in world.objects if o.patch]
    assert patches and all(o.instance >= PATCH_BASE for o in patches)
    faces = world.instance == patches[0].instance
    assert faces.sum() > 100


def test_mixed_pixel_is_energy_weighted_average():
    r = np.array([[10.0, 10.5, np.inf, 30.0]])
    energy = np.array([[0.4, 0.2, 0.0, 0.4]])
    active = np.isfinite(r)
    mean, total, member = _echo(r, energy, active, window=1.0)
    assert np.isclose(mean[0], (0.4 * 10 + 0.2 * 10.5) / 0.6)
    assert np.isclose(total[0], 0.6)
    np.testing.assert_array_equal(member[0], [True, True, False, False])


def test_range_noise_matches_sensor_spec(small_world):
    # a noise-only check: a sensor with 10 cm noise spreads ground returns ~5x wider than 2 cm
    poses = path_poses(small_world, 6.0, margin=8.0)[:1]
    spreads = []
    for noise in (0.02, 0.10):
        sensor = SensorSpec(n_firings=360, range_noise=noise, divergence=1e-6)
        logs = [render_log(small_world, poses, sensor, seed=s) for s in (1, 2)]
        both = logs[0].hit & logs[1].hit & (logs[0].attributes["label"] == CLASS_ID["ground"])
        spreads.append(np.std(logs[0].ranges[both] - logs[1].ranges[both]) / np.sqrt(2))
    # tolerance: 25 % on a sample of several thousand differences
    assert abs(spreads[0] - 0.02) < 0.005 and abs(spreads[1] - 0.10) < 0.025
