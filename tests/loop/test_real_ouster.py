"""The loop on the real Ouster frame: the range-image mesh, the column split, and the development path."""

from __future__ import annotations

import numpy as np
import pytest

from mi_lidar.core.log import Log
from mi_lidar.loop.real_ouster import FILLED, column_log, ouster_development_path, range_image_mesh


def synthetic_frame() -> Log:
    """A 16 x 256 spinning scan 1.5 m above flat ground, with a cylindrical wall 4 m away in columns 80-99.

    Beams look from -5 deg to -25 deg in 1.33 deg steps and fire every 1.4 deg (an OS-1-32's
    spacing). Neighbouring ground returns lie up to 2.5 m apart in range (grazing incidence), and
    at the wall's edges the range jumps from 4 m to the ground behind it (up to 17 m).
    """
    elevation = np.radians(np.linspace(-5, -25, 16))[:, None]
    azimuth = np.radians(np.arange(256) * 360 / 256)[None, :]
    directions = np.stack(
        np.broadcast_arrays(
            np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)
        ),
        -1,
    )
    ranges = 1.5 / -directions[..., 2]
    wall = (np.arange(256) >= 80) & (np.arange(256) < 100)
    ranges[:, wall] = np.minimum(ranges[:, wall], 4.0 / np.cos(elevation))
    return Log(
        poses=np.eye(4)[None],
        directions=directions,
        ranges=ranges[None],
        hit=np.ones((1, 16, 256), bool),
        times=np.zeros((1, 16, 256)),
    )


def test_mesh_joins_neighbouring_returns_in_the_world_frame_and_skips_quads_with_a_miss():
    log = synthetic_frame()
    log.hit[0, 5, 40] = False
    log.poses[0, :3, 3] = [10.0, -2.0, 0.5]
    columns = np.arange(0, 256, 2)
    mesh = range_image_mesh(log, columns)
    assert len(mesh.faces) == 15 * 128 * 2 - 6  # the missing return at (5, 40) removes the 6 faces around it
    vertex = mesh.vertices.reshape(16, 128, 3)
    expected = log.ranges[0][:, columns, None] * log.directions[0][:, columns] + [10.0, -2.0, 0.5]
    np.testing.assert_allclose(vertex[log.hit[0][:, columns]], expected[log.hit[0][:, columns]], atol=1e-4)
    assert not np.any(mesh.faces == 5 * 128 + 20)  # no face uses the vertex without a return
    r = np.linalg.norm(mesh.vertices - log.poses[0, :3, 3], axis=1)[mesh.faces]
    assert (r.max(1) / r.min(1)).max() > 4  # jump-edge faces are kept (calibration makes them permeable)


def test_column_log_keeps_the_rays_of_its_columns():
    """Ranges, directions and per-ray attributes (an Ouster frame's REFLECTIVITY, for the intensity residuals)."""
    log = synthetic_frame()
    log.attributes["reflectivity"] = np.arange(log.ranges.size).reshape(log.shape)
    sub = column_log(log, np.arange(1, 256, 2))
    assert sub.shape == (1, 16, 128)
    np.testing.assert_array_equal(sub.ranges[0], log.ranges[0][:, 1::2])
    np.testing.assert_array_equal(sub.directions[0], log.directions[0][:, 1::2])
    np.testing.assert_array_equal(sub.attributes["reflectivity"][0], log.attributes["reflectivity"][0][:, 1::2])


def test_holes_are_closed_at_a_neighbour_range_and_their_faces_labelled():
    log = synthetic_frame()
    log.hit[0, 5, 40] = False
    columns = np.arange(0, 256, 2)
    mesh = range_image_mesh(log, columns, fill_holes=True)
    assert len(mesh.faces) == 15 * 128 * 2  # no hole
    assert np.sum(mesh.label == FILLED) == 6  # the faces around the filled sample
    filled = mesh.vertices.reshape(16, 128, 3)[5, 20]
    np.testing.assert_allclose(
        filled, log.ranges[0, 5, 38] * log.directions[0, 5, 40], atol=1e-4
    )  # left neighbour's range


def test_faces_are_labelled_by_how_many_of_their_corners_close_a_hole():
    """Rows 1 and 2 lost (open space between two returning rows): row 1 is filled from row 0, row 2 from row 3.

    Every quad between rows 0 and 1 gives a face with one filled corner and one with two; between rows 1
    and 2 both faces are all fills; between rows 2 and 3 one face has two filled corners and one has one.
    """
    log = synthetic_frame()
    log.hit[0, 1:3] = False
    mesh = range_image_mesh(log, np.arange(0, 256, 2), fill_holes=True)
    assert len(mesh.faces) == 15 * 128 * 2
    assert np.bincount(mesh.label, minlength=4).tolist() == [12 * 256, 256, 256, 256]
    vertex = mesh.vertices.reshape(16, 128, 3)
    np.testing.assert_allclose(vertex[1], log.ranges[0, 0, ::2, None] * log.directions[0, 1, ::2], atol=1e-4)
    np.testing.assert_allclose(vertex[2], log.ranges[0, 3, ::2, None] * log.directions[0, 2, ::2], atol=1e-4)


@pytest.mark.slow
def test_calibrated_model_beats_the_bare_mesh_in_nll_and_samples_like_the_sensor(shared_data):
    """The regression test of the real-frame loop (issue 13; docs/loop_results.md).

    The bare mesh (columns 0 mod 4, sigma 1 cm) scores 11.87 nats per test ray and samples with a median
    |range error| of 6.2 cm; the loop used to end at 5.51 nats with 41 % of its mass on near outliers and
    a sampled median error of 2.04 m, then at 4.39 nats with 16 cm (corner returns with a fitted 8 cm
    spread). The calibrated model must be better in NLL by 3 nats (measured: 4.5) and sample like the
    sensor: histogram match and hit/miss F1 no worse than the bare mesh's, the sampled median error within
    10 % of the bare mesh's (measured: +3 %; -1 to +4 % over sampling seeds 0-4).
    """
    import mitsuba as mi

    import mi_lidar
    from mi_lidar.io import read_any
    from mi_lidar.loop.compare import compare
    from mi_lidar.scene.dicts import scene_dict

    log = read_any(shared_data / "ouster" / "OS-1-32-G_v2.1.1_1024x10.pcap")
    columns = np.arange(log.shape[2])
    test = column_log(log, columns[columns % 2 == 1])
    bare_scene = mi.load_dict(scene_dict({"map": range_image_mesh(log, columns[columns % 4 == 0])}))
    bare = compare(test, bare_scene, mi_lidar.SensorModel(range_sigma=0.01, max_range=120.0, max_segments=4)).headline
    path = ouster_development_path(log)
    final = compare(test, mi.load_dict(scene_dict({"map": path.mesh})), path.model).headline
    kept = [row for row in path.rows if not row.rejected]
    assert all(b.nll < a.nll for a, b in zip(kept, kept[1:]))  # every kept step lowers the test NLL
    assert final["nll"] < bare["nll"] - 3.0
    assert final["histogram_l1"] <= bare["histogram_l1"] and final["f1"] >= bare["f1"] - 0.01
    assert final["range_error_median"] <= 1.1 * bare["range_error_median"]


def test_the_realism_guard_rejects_a_step_and_restores_the_model():
    """A guarded step that does not lower the calibration NLL is marked rejected: its effect is removed and the
    other effects get their parameters back (the refit moved them)."""
    import mitsuba as mi

    from mi_lidar.core.effects import make_effect
    from mi_lidar.core.elements import ElementTable
    from mi_lidar.core.rays import LogRays
    from mi_lidar.core.sensor_model import SensorModel
    from mi_lidar.loop.development import Scored, effect_step, ray_subset
    from mi_lidar.scene.dicts import scene_dict

    log = synthetic_frame()
    log.ranges[0] += np.random.default_rng(0).normal(0, 0.05, log.ranges[0].shape)
    mesh = range_image_mesh(log, np.arange(0, 256, 4))
    scene = mi.load_dict(scene_dict({"map": mesh}))
    table, rays = ElementTable.from_scene(scene), LogRays.from_log(log)
    train, test = (
        Scored(scene, table, ray_subset(rays, keep), len(mesh.faces))
        for keep in (rays.column % 4 == 2, rays.column % 2 == 1)
    )
    noise = make_effect("range_noise", law="constant", sigma0=0.2)
    model = SensorModel(range_sigma=0.01, max_segments=2, effects=[noise])
    kept = effect_step("mesh", "noise", train, test, model, 30, lambda m: None, guard=(np.inf, train.samples(model)))
    assert not kept.rejected and kept.fitted["range_noise.sigma0"] < 0.2  # the fit moved sigma0 towards 5 cm
    sigma0 = float(np.asarray(noise["sigma0"])[0])
    model.effects = model.effects + [make_effect("range_bias", bias=0.3)]
    row = effect_step("mesh", "bias", train, test, model, 5, lambda m: None, guard=(-np.inf, train.samples(model)))
    assert row.rejected == "calibration NLL did not fall"
    assert [e.name for e in model.effects] == ["range_noise"]
    assert float(np.asarray(noise["sigma0"])[0]) == pytest.approx(sigma0)
