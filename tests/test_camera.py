"""Camera and Lidar from one scene: projection consistent with Mitsuba's own camera."""

import mitsuba as mi
import numpy as np
import pytest
from typer.testing import CliRunner

import mi_lidar
from mi_lidar.cli import app
from mi_lidar.core.errors import ParameterError
from mi_lidar.scene.camera import PinholeCamera, camera_lidar_frame

from .conftest import SCENES


def test_projected_lidar_returns_match_the_camera_depth_image():
    scene = mi_lidar.load_scene(SCENES / "urban_street.xml")
    camera = PinholeCamera.look_at([0.5, -0.5, 2.2], [10, 3, 1.5], width=320, height=200)
    frame = camera_lidar_frame(scene, camera, spp=4)
    distance = np.asarray(mi.render(scene, sensor=camera.sensor(spp=1), integrator=mi.load_dict({"type": "depth"})))[
        ..., 0
    ]
    uv, visible = frame["uv"][frame["visible"]], frame["visible"]
    assert visible.sum() > 500
    pixel = np.floor(uv).astype(int)
    rendered = distance[pixel[:, 1], pixel[:, 0]]
    expected = np.linalg.norm(frame["points"][visible] - camera.to_world[:3, 3], axis=1)
    # Away from silhouettes and permeable canopies the camera sees the surface the Lidar hit:
    # the median relative difference is a few pixel footprints (< 2%).
    assert np.median(np.abs(rendered - expected) / expected) < 0.02


def test_camera_lidar_command_writes_a_frame(tmp_path):
    result = CliRunner().invoke(
        app,
        [
            "camera-lidar",
            str(SCENES / "urban_street.xml"),
            "--out",
            str(tmp_path),
            "--width",
            "160",
            "--height",
            "100",
            "--spp",
            "4",
        ],
    )
    assert result.exit_code == 0, result.stdout
    for name in ("image.png", "image.exr", "points.ply", "scan.npz", "overlay.png", "calib.json"):
        assert (tmp_path / name).stat().st_size > 100


def test_an_off_centre_principal_point_renders_where_project_puts_it():
    """A small glowing sphere lands at the pixel ``project`` gives, with the principal point moved by
    (-23, +14) px; the image centroid of the sphere matches its projected centre to 0.3 px (the
    sphere's image is a 3 px disc sampled at 16 spp)."""
    scene = mi.load_dict(
        {
            "type": "scene",
            "integrator": {"type": "direct"},
            "glow": {
                "type": "sphere",
                "center": [6.0, 0.8, 1.3],
                "radius": 0.05,
                "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1.0}},
            },
        }
    )
    for centre in (None, (77.0, 64.0)):
        camera = PinholeCamera.look_at([0, 0, 1], [6, 0, 1], width=200, height=100, fov_deg=60, principal_point=centre)
        image = np.asarray(mi.render(scene, sensor=camera.sensor(spp=16)))[..., 0]
        rows, columns = np.mgrid[0 : image.shape[0], 0 : image.shape[1]] + 0.5  # pixel centres
        measured = np.array([(image * columns).sum(), (image * rows).sum()]) / image.sum()
        uv, _, visible = camera.project(np.array([[6.0, 0.8, 1.3]]))
        assert visible[0]
        np.testing.assert_allclose(measured, uv[0], atol=0.3)
    with pytest.raises(ParameterError, match="principal point"):
        PinholeCamera(np.eye(4), 100, 50, principal_point=(120.0, 10.0))
