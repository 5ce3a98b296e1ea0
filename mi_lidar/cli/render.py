"""Verbs that make scans: ``render``, ``simulate``, ``camera-lidar`` and ``demo``."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import typer
from rich.table import Table

from mi_lidar.cli.app import app, console, density_option, say
from mi_lidar.cli.progress import progress
from mi_lidar.core.errors import MiLidarError, ParameterError

MAX_SEED = 2**32 - 1  # Mitsuba's render seed is a 32-bit unsigned integer
LOOP_TITLE = "The loop: a hidden effect, its diagnosis, the error before and after"  # fits 80 columns


def scan_summary(log, title: str, elapsed: float | None = None) -> Table:
    """A rich table summarising a log: rays, hit fraction, range quantiles, returns per label."""
    table = Table(title=title, show_header=True, header_style="bold")
    table.add_column("quantity")
    table.add_column("value", justify="right")
    s, h, w = log.shape
    hits = log.hit
    ranges = log.ranges[hits]
    table.add_row("scans x beams x firings", f"{s} x {h} x {w}")
    table.add_row("rays", f"{log.n_rays:,}")
    table.add_row("returns", f"{hits.sum():,} ({hits.mean():.1%})")
    if ranges.size:
        q = np.quantile(ranges, [0.0, 0.5, 1.0])
        table.add_row("range min / median / max (m)", f"{q[0]:.2f} / {q[1]:.2f} / {q[2]:.2f}")
    if "segments" in log.attributes:
        table.add_row("rays passing >= 1 element", f"{np.mean(log.attributes['segments'] > 1):.1%}")
    if "label" in log.attributes and ranges.size:
        labels, counts = np.unique(log.attributes["label"][hits], return_counts=True)
        pairs = (f"{lab}:{c:,}" for lab, c in zip(labels, counts))  # no space, so no line ends with '5:'
        table.add_row("returns per label", ", ".join(pairs))
    if elapsed is not None:
        table.add_row("time (s)", f"{elapsed:.2f} ({ray_rate(log.n_rays, elapsed)})")
    return table


def ray_rate(rays: int, seconds: float) -> str:
    """Rays per second for a person to read: ``1.7 M rays/s``, or whole rays below 0.1 M (``23,000 rays/s``)."""
    rate = rays / max(seconds, 1e-9)
    return f"{rate / 1e6:.1f} M rays/s" if rate >= 1e5 else f"{rate:,.0f} rays/s"


def write_scan_outputs(log, out: Path, scene_name: str) -> list[Path]:
    """Write ``scan.exr``, ``points.ply``, ``scan.bin`` (KITTI), ``scan.npz`` and PNG previews of scan 0.

    The folder is made first and removed again while empty when a write fails (a full disk: it was left behind).
    """
    from mi_lidar.core.atomic import output_folder
    from mi_lidar.core.channels import INTEGER_CHANNELS
    from mi_lidar.io import birds_eye_png, range_image_png, write_exr, write_kitti_bin, write_ply

    with output_folder(out):
        scan = log.scan(0)
        channels = {"range": scan.ranges[0], "hit": scan.hit[0].astype(np.float32)}
        channels.update({k: v[0] for k, v in scan.attributes.items()})
        exr = write_exr(
            out / "scan.exr",
            {k: np.asarray(v, np.float32) if k not in INTEGER_CHANNELS else v for k, v in channels.items()},
        )
        hit = scan.hit[0]
        points = scan.points_world()[0][hit]  # float64: write_ply keeps it for georeferenced points
        beam = np.broadcast_to(np.arange(hit.shape[0])[:, None], hit.shape)[hit].astype(np.uint16)
        attributes = {"range": scan.ranges[0][hit], "ring": beam}
        attributes.update({k: v[0][hit] for k, v in scan.attributes.items()})
        ply = write_ply(out / "points.ply", points, attributes)
        kitti = write_kitti_bin(out / "scan.bin", scan.points_sensor()[0][hit], None)
        npz = scan.save(out / "scan.npz")
        png_range = range_image_png(out / "range.png", scan.ranges[0], title=f"{scene_name}: range (m)")
        values = scan.attributes["label"][0][hit] if "label" in scan.attributes else None
        png_bev = birds_eye_png(
            out / "birds_eye.png",
            points,
            values=values,
            title=f"{scene_name}: returns by label",
            value_label="label",
            categorical=True,
        )
        return [exr, ply, kitti, npz, png_range, png_bev]


@app.command(rich_help_panel="Make scans")
def render(
    scene: Path = typer.Argument(..., help="Scene XML with a `lidar` sensor.", exists=True, dir_okay=False),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder."),
    seed: int = typer.Option(0, metavar="N", min=0, max=MAX_SEED, help="Random seed (same seed, same scan)."),
    pattern: str | None = typer.Option(
        None, help="Override the firing pattern, e.g. `hdl32e`, `os1-32`, `planar-360`."
    ),
    density: str | None = density_option(),
):
    """Render one scan of SCENE and write `scan.exr`, `points.ply`, `scan.bin`, `scan.npz` and PNG previews.

    Examples:

    ```
    mi-lidar render scenes_xml/offroad.xml --out out/offroad

    mi-lidar render scenes_xml/urban_street.xml --out out/street \\
        --pattern hdl64e --seed 3
    ```
    """
    import mitsuba as mi

    from mi_lidar.core.channels import tensor_to_numpy
    from mi_lidar.core.frames import scene_origin, shift_poses
    from mi_lidar.core.log import Log
    from mi_lidar.plugins.lidar_integrator import LidarIntegrator
    from mi_lidar.scene import load_scene, scene_lidar_sensor, use_density
    from mi_lidar.scene.simulation import simulate

    loaded = use_density(load_scene(scene), density)
    start = time.perf_counter()
    sensor = scene_lidar_sensor(loaded)
    if pattern is None:
        if sensor is None:
            raise MiLidarError(f'{scene}: the scene has no `lidar` sensor; add <sensor type="lidar"> or pass --pattern')
        if not isinstance(loaded.integrator(), LidarIntegrator):  # (Mitsuba's own exception came as a traceback)
            kind = type(loaded.integrator()).__name__ if loaded.integrator() is not None else "none"
            raise MiLidarError(
                f"{scene}: the scene's integrator is {kind}, not a lidar_integrator; add <integrator type=\""
                'lidar_integrator"/> or pass --pattern'
            )
        channels = tensor_to_numpy(mi.render(loaded, seed=seed))
        pat = sensor.pattern
        log = Log(
            poses=shift_poses(sensor.to_world_matrix[None], -scene_origin(loaded)),  # the world pose
            directions=pat.directions()[None],
            origins=pat.origins()[None],
            ranges=channels.pop("range")[None],
            hit=channels.pop("hit")[None],
            times=pat.time[None],
            attributes={k: v[None] for k, v in channels.items()},
            sensor={"pattern": pat.name, "seed": seed},
        )
    else:
        log = simulate(loaded, pattern, seed=seed)
    elapsed = time.perf_counter() - start
    files = write_scan_outputs(log, out, scene.stem)
    console.print(scan_summary(log, f"{scene.name} (seed {seed})", elapsed))
    for path in files:
        console.print(f"wrote {path}")


@app.command(rich_help_panel="Make scans")
def simulate(
    scene: Path = typer.Argument(..., help="Scene XML.", exists=True, dir_okay=False),
    poses: Path = typer.Option(
        ...,
        help="Sensor-to-world poses: `.npy` (S, 4, 4), a saved log (`.npz`: its poses), text with 16 numbers per "
        "line, or a KITTI poses file (12 per line). They replace the scene sensor's pose, its height included "
        "(offroad.xml mounts the VLP-16 at z = 2 m).",
        exists=True,
        dir_okay=False,
    ),
    out: Path = typer.Option(
        ...,
        "--out",
        "-o",
        help="Output log: `.npz` (every scan) or a ROS 2 bag (`.bag` folder); with one pose also `.ply`, `.pcd`, "
        "`.bin`, `.las`, `.exr`.",
    ),
    seed: int = typer.Option(0, metavar="N", min=0, help="Random seed."),
    pattern: str | None = typer.Option(None, help="Firing pattern (default: the scene sensor's)."),
    density: str | None = density_option(),
    effect: str | None = typer.Option(
        None,
        "--effect",
        help="Effects to add to the scene's, e.g. `incidence_dropout(gamma=2)`: a log with an effect the scene's "
        "model lacks, for `compare` and `diagnose` to find.",
    ),
):
    """Simulate one scan per pose and write a log (`.npz`, see `mi_lidar.core.log`, or another format by extension).

    The poses replace the scene sensor's pose (give them at the sensor's mounting height).

    Examples:

    ```
    mi-lidar simulate scenes_xml/offroad.xml --poses poses.txt --out drive.npz

    mi-lidar simulate scenes_xml/offroad.xml --poses poses.txt \\
        --out biased.npz --effect "range_bias(bias=0.05)"

    mi-lidar simulate scenes_xml/indoor_planar.xml --poses room_poses.txt \\
        --out room.npz --pattern planar-180
    ```
    """
    from mi_lidar.io import read_poses, write_any
    from mi_lidar.io.dispatch import log_output_format
    from mi_lidar.scene import load_scene, use_density, use_effects
    from mi_lidar.scene.simulation import simulate as run

    loaded = use_effects(use_density(load_scene(scene), density), effect)
    pose_array = read_poses(poses)
    fmt = log_output_format(out, len(pose_array))
    start = time.perf_counter()
    with progress("simulating scans", total=len(pose_array)) as update:
        log = run(
            loaded,
            pattern,
            poses=pose_array,
            seed=seed,
            progress=lambda done, total: update(done, total),
        )
    elapsed = time.perf_counter() - start
    path = write_any(log, out, fmt=fmt)
    console.print(scan_summary(log, f"{scene.name}: {len(pose_array)} scans (seed {seed})", elapsed))
    console.print(f"wrote {path}")


def parse_vector(text: str, name: str) -> list[float]:
    """Three comma-separated numbers (m); raise a ParameterError naming the option otherwise."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3 or not all(np.isfinite(values)):
        raise ParameterError(f"{name} needs three comma-separated finite numbers (m), e.g. 0,0,1.8; got {text!r}")
    return values


@app.command("camera-lidar", rich_help_panel="Make scans")
def camera_lidar(
    scene: Path = typer.Argument(
        ..., help="Scene XML with a `lidar` sensor (add emitters to light the camera).", exists=True, dir_okay=False
    ),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder."),
    camera_from: str = typer.Option("0,0,1.8", "--from", help="Camera position x,y,z (m)."),
    camera_to: str = typer.Option("10,0,1.5", "--to", help="Point the camera looks at x,y,z (m)."),
    width: int = typer.Option(640, metavar="N", min=1, max=8192, help="Image width (pixels)."),
    height: int = typer.Option(400, metavar="N", min=1, max=8192, help="Image height (pixels)."),
    fov: float = typer.Option(70.0, metavar="X", min=1.0, max=179.0, help="Horizontal field of view (deg)."),
    spp: int = typer.Option(64, metavar="N", min=1, max=4096, help="Camera samples per pixel (one render pass each)."),
    seed: int = typer.Option(0, metavar="N", min=0, help="Random seed."),
):
    """Synthetic camera + Lidar data from one scene: image, scan, projection and calibration (KITTI-style).

    Writes `image.png` (sRGB), `image.exr` (linear), `points.ply` (world frame), `scan.npz`,
    `overlay.png` (Lidar returns over the image, coloured by depth) and `calib.json` (K, lidar_to_camera).

    Example:

    ```
    mi-lidar camera-lidar scenes_xml/urban_street.xml --out out/frame \\
        --from 0,0,1.8 --to 10,2,1.5
    ```
    """
    from mi_lidar.core.strict_json import write_json
    from mi_lidar.io import write_exr, write_ply
    from mi_lidar.io.preview import overlay_png, rgb_png
    from mi_lidar.scene import load_scene
    from mi_lidar.scene.camera import PinholeCamera, camera_lidar_frame

    loaded = load_scene(scene)
    camera = PinholeCamera.look_at(
        parse_vector(camera_from, "--from"), parse_vector(camera_to, "--to"), width=width, height=height, fov_deg=fov
    )
    with progress("rendering the camera image and the Lidar scan"):
        frame = camera_lidar_frame(loaded, camera, seed=seed, spp=spp)
    out.mkdir(parents=True, exist_ok=True)
    files = [
        rgb_png(out / "image.png", frame["image"]),
        write_exr(out / "image.exr", {c: frame["image"][..., i] for i, c in enumerate("RGB")}),
        write_ply(out / "points.ply", frame["points"].astype(np.float32)),
        frame["log"].save(out / "scan.npz"),
        overlay_png(
            out / "overlay.png",
            frame["image"],
            frame["uv"][frame["visible"]],
            frame["depth"][frame["visible"]],
            title=f"{scene.name}: Lidar returns over the camera image",
        ),
    ]
    calib = {
        "K": frame["K"].tolist(),
        "lidar_to_camera": frame["lidar_to_camera"].tolist(),
        "camera_convention": "OpenCV (x right, y down, z forward)",
        "width": width,
        "height": height,
    }
    files.append(write_json(out / "calib.json", calib))
    console.print(f"{int(frame['visible'].sum()):,} of {len(frame['points']):,} Lidar returns fall in the image")
    for path in files:
        console.print(f"wrote {path}")


@app.command(rich_help_panel="Make scans")
def demo(
    out: Path = typer.Option(Path("demo_out"), "--out", "-o", help="Output folder."),
    seed: int = typer.Option(0, metavar="N", min=0, max=MAX_SEED, help="Random seed."),
):
    """The main job of `make demo`: render the bundled off-road scene, then run the loop on a log with a hidden effect.

    Example:

    ```
    mi-lidar demo --out demo_out
    ```
    """
    from mi_lidar.loop.demo import run_demo
    from mi_lidar.scene import bundled_scene

    render(bundled_scene("offroad.xml"), out, seed=seed, pattern=None, density=None)
    console.rule(LOOP_TITLE)
    run_demo(out=out / "loop", echo=say)
