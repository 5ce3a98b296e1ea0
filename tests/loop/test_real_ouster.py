"""The loop on the real Ouster frame: the range-image mesh, the column split, and the development path."""

from __future__ import annotations

import numpy as np

from mi_lidar.core.log import Log
from mi_lidar.loop.real_ouster import column_log, ouster_development_path, range_image_mesh


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


def test_development_path_on_the_real_frame_falls_and_ends_finite(shared_data):
    """The path of docs/loop_results.md (default 1,500 Adam steps per fit; 300 leave a refit short of its optimum).

    The bare mesh cannot produce the returns that have no face on their ray: under the one floor
    each costs 20.7 nats, so the first row is the worst; every later row may rise by at most 0.005
    nats on the calibration and the test columns.
    """
    from mi_lidar.io import read_any

    log = read_any(shared_data / "ouster" / "OS-1-32-G_v2.1.1_1024x10.pcap")
    path = ouster_development_path(log)
    nll, train = [row.nll for row in path.rows], [row.train_nll for row in path.rows]
    assert path.rows[0].fitted["test returns at the floor (no face near their range)"] > 1000 and nll[0] > nll[1]
    assert all(np.isfinite(nll))
    for values in (nll, train):
        assert all(b <= a + 0.005 for a, b in zip(values[1:], values[2:]))
    assert nll[-1] < nll[1] - 0.5  # proportional noise and per-face hit probabilities
    assert np.all((path.mesh.p_hit > 0) & (path.mesh.p_hit < 1))
