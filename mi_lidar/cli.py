"""The ``mi-lidar`` command line (Typer): render, simulate, convert, inspect, demo."""

from __future__ import annotations

import contextlib
import os
import time
from pathlib import Path
from typing import Optional

import numpy as np
import typer
from rich.console import Console
from rich.table import Table

from .errors import MiLidarError

app = typer.Typer(
    name="mi-lidar",
    help="Lidar simulation on Mitsuba 3: render scans from XML scenes, simulate logs, convert real sensor data.",
    no_args_is_help=True,
    add_completion=False,
    rich_markup_mode="markdown",
)
console = Console()

DEFAULT_SCENE = Path(__file__).resolve().parents[1] / "scenes_xml" / "offroad.xml"


def _versions() -> dict[str, str]:
    import drjit as dr
    import mitsuba as mi

    from . import __version__

    llvm = os.environ.get("DRJIT_LIBLLVM_PATH", "system default")
    with contextlib.suppress(RuntimeError):  # the backend reports no version before it is initialised
        llvm = "{}.{}.{} ({})".format(*dr.detail.llvm_version(), llvm)
    return {"mi-lidar": __version__, "Mitsuba": mi.__version__, "Dr.Jit": dr.__version__,
            "variant": str(mi.variant()), "LLVM": llvm}


def _version_callback(value: bool):
    if value:
        for name, version in _versions().items():
            console.print(f"{name:9s} {version}")
        raise typer.Exit()


@app.callback()
def main(
    version: bool = typer.Option(False, "--version", callback=_version_callback, is_eager=True,
                                 help="Print the versions of mi-lidar, Mitsuba, Dr.Jit, the variant and LLVM."),
):
    """Lidar simulation for robot application development."""


def _fail(exc: Exception):
    console.print(f"[bold red]error:[/] {exc}")
    raise typer.Exit(code=2)


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
        table.add_row("returns per label", ", ".join(f"{lab}: {c:,}" for lab, c in zip(labels, counts)))
    if elapsed is not None:
        table.add_row("time (s)", f"{elapsed:.2f} ({log.n_rays / max(elapsed, 1e-9) / 1e6:.1f} M rays/s)")
    return table


def write_scan_outputs(log, out: Path, scene_name: str) -> list[Path]:
    """Write ``scan.exr``, ``points.ply``, ``scan.bin`` (KITTI), ``scan.npz`` and PNG previews of scan 0."""
    from .channels import INTEGER_CHANNELS
    from .io import birds_eye_png, range_image_png, write_exr, write_kitti_bin, write_ply

    out.mkdir(parents=True, exist_ok=True)
    scan = log.scan(0)
    channels = {"range": scan.ranges[0], "hit": scan.hit[0].astype(np.float32)}
    channels.update({k: v[0] for k, v in scan.attributes.items()})
    exr = write_exr(out / "scan.exr", {k: np.asarray(v, np.float32) if k not in INTEGER_CHANNELS else v
                                       for k, v in channels.items()})
    hit = scan.hit[0]
    points = scan.points_world()[0][hit].astype(np.float32)
    beam = np.broadcast_to(np.arange(hit.shape[0])[:, None], hit.shape)[hit].astype(np.uint16)
    attributes = {"range": scan.ranges[0][hit], "ring": beam}
    attributes.update({k: v[0][hit] for k, v in scan.attributes.items()})
    ply = write_ply(out / "points.ply", points, attributes)
    kitti = write_kitti_bin(out / "scan.bin", scan.points_sensor()[0][hit], None)
    npz = scan.save(out / "scan.npz")
    png_range = range_image_png(out / "range.png", scan.ranges[0], title=f"{scene_name}: range (m)")
    values = scan.attributes["label"][0][hit] if "label" in scan.attributes else None
    png_bev = birds_eye_png(out / "birds_eye.png", points, values=values, title=f"{scene_name}: returns by label")
    return [exr, ply, kitti, npz, png_range, png_bev]


@app.command()
def render(
    scene: Path = typer.Argument(..., help="Scene XML with a `lidar` sensor.", exists=True, dir_okay=False),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder."),
    seed: int = typer.Option(0, help="Random seed (same seed, same scan)."),
    pattern: Optional[str] = typer.Option(None, help="Override the firing pattern, e.g. `hdl32e`, `os1-32`, `planar-360`."),
):
    """Render one scan of SCENE and write `scan.exr`, `points.ply`, `scan.bin`, `scan.npz` and PNG previews.

    Examples:

        mi-lidar render scenes_xml/offroad.xml --out out/offroad

        mi-lidar render scenes_xml/urban_street.xml --out out/street --pattern hdl64e --seed 3
    """
    import mitsuba as mi

    from .channels import tensor_to_numpy
    from .log import Log
    from .scene import load_scene, scene_lidar_sensor
    from .simulate import simulate

    try:
        loaded = load_scene(scene)
        start = time.perf_counter()
        sensor = scene_lidar_sensor(loaded)
        if pattern is None:
            if sensor is None:
                raise MiLidarError(f"{scene}: the scene has no `lidar` sensor; add <sensor type=\"lidar\"> or pass --pattern")
            channels = tensor_to_numpy(mi.render(loaded, seed=seed))
            pat = sensor.pattern
            log = Log(
                poses=sensor.to_world_matrix[None], directions=pat.directions()[None], origins=pat.origins()[None],
                ranges=channels.pop("range")[None], hit=channels.pop("hit")[None], times=pat.time[None],
                attributes={k: v[None] for k, v in channels.items()}, sensor={"pattern": pat.name, "seed": seed},
            )
        else:
            log = simulate(loaded, pattern, seed=seed)
        elapsed = time.perf_counter() - start
        files = write_scan_outputs(log, out, scene.stem)
    except (MiLidarError, ValueError) as exc:
        _fail(exc)
    console.print(scan_summary(log, f"{scene.name} (seed {seed})", elapsed))
    for path in files:
        console.print(f"wrote {path}")


def _read_poses(path: Path) -> np.ndarray:
    from .io import read_kitti_poses, read_pose_matrices

    if path.suffix == ".npy":
        return read_pose_matrices(path)
    first = next((line.split() for line in path.read_text().splitlines() if line.strip()), [])
    return read_kitti_poses(path) if len(first) == 12 else read_pose_matrices(path)


@app.command()
def simulate(
    scene: Path = typer.Argument(..., help="Scene XML.", exists=True, dir_okay=False),
    poses: Path = typer.Option(..., help="Sensor poses: `.npy` (S, 4, 4), text with 16 numbers per line, or a KITTI poses file (12 per line).", exists=True, dir_okay=False),
    out: Path = typer.Option(..., "--out", "-o", help="Output log (`.npz`)."),
    seed: int = typer.Option(0, help="Random seed."),
    pattern: Optional[str] = typer.Option(None, help="Firing pattern (default: the scene sensor's)."),
):
    """Simulate one scan per pose and write a log (`.npz`, see `mi_lidar.log`).

    Examples:

        mi-lidar simulate scenes_xml/offroad.xml --poses poses.txt --out drive.npz

        mi-lidar simulate scenes_xml/indoor_planar.xml --poses kitti_poses.txt --out room.npz --pattern planar-180
    """
    from rich.progress import Progress

    from .scene import load_scene
    from .simulate import simulate as run

    try:
        loaded = load_scene(scene)
        pose_array = _read_poses(poses)
        start = time.perf_counter()
        with Progress(console=console, transient=True) as progress:
            task = progress.add_task("simulating scans", total=len(pose_array))
            log = run(loaded, pattern, poses=pose_array, seed=seed,
                      progress=lambda done, total: progress.update(task, completed=done))
        elapsed = time.perf_counter() - start
        path = log.save(out)
    except (MiLidarError, ValueError, OSError) as exc:
        _fail(exc)
    console.print(scan_summary(log, f"{scene.name}: {len(pose_array)} scans (seed {seed})", elapsed))
    console.print(f"wrote {path}")


@app.command()
def convert(
    source: Path = typer.Argument(..., help="Input: .pcap (Ouster/Velodyne), CARMEN .log[.gz], .bin, .ply, .pcd, .las, ROS 2 bag folder, .npz log, .exr.", exists=True),
    target: Path = typer.Argument(..., help="Output file; its extension picks the format unless --to is given."),
    to: Optional[str] = typer.Option(None, help="Output format: npz, bin, ply, pcd, las, rosbag2, exr, png."),
    scan: Optional[int] = typer.Option(None, help="Scan to write when the output holds one scan (required for multi-scan logs)."),
    metadata: Optional[Path] = typer.Option(None, help="Ouster metadata JSON (default: next to the pcap)."),
    calibration: Optional[Path] = typer.Option(None, help="Velodyne calibration YAML (default: next to the pcap)."),
):
    """Convert a Lidar file to another format, keeping misses explicit where the format allows.

    Examples:

        mi-lidar convert ../shared/data/carmen/intel-corrected.log.gz intel.npz

        mi-lidar convert ../shared/data/ouster/OS-1-32-G_v2.1.1_1024x10.pcap frame.pcd --scan 0

        mi-lidar convert drive.npz drive_bag --to rosbag2
    """
    from .io import convert as run

    options = {k: v for k, v in (("metadata", metadata), ("calibration", calibration)) if v is not None}
    try:
        with console.status(f"converting {source.name}"):
            path = run(source, target, to=to, scan=scan, **options)
    except (MiLidarError, ValueError, OSError) as exc:
        _fail(exc)
    console.print(f"wrote {path}")


@app.command()
def info(
    source: Path = typer.Argument(..., help="Any file `convert` reads.", exists=True),
    metadata: Optional[Path] = typer.Option(None, help="Ouster metadata JSON (default: next to the pcap)."),
    calibration: Optional[Path] = typer.Option(None, help="Velodyne calibration YAML (default: next to the pcap)."),
):
    """Summarise a Lidar file: sensor, beams, firings, scans, miss fraction, range span, pose extents.

    Examples:

        mi-lidar info ../shared/data/velodyne/velodyne_vlp16.pcap

        mi-lidar info drive.npz
    """
    from .io import info as run

    options = {k: v for k, v in (("metadata", metadata), ("calibration", calibration)) if v is not None}
    try:
        with console.status(f"reading {source.name}"):
            summary = run(source, **options)
    except (MiLidarError, ValueError, OSError) as exc:
        _fail(exc)
    table = Table(title=str(source.name), show_header=True, header_style="bold")
    table.add_column("quantity")
    table.add_column("value", justify="right")
    s, h, w = summary["shape"]
    rows = [
        ("format", summary["format"]), ("sensor", summary["sensor"]),
        ("scans x beams x firings", f"{s} x {h} x {w}"), ("rays", f"{summary['rays']:,}"),
        ("miss fraction", f"{summary['miss_fraction']:.1%}"), ("invalid cells", f"{summary['invalid_fraction']:.1%}"),
    ]
    if summary["range_m"]:
        rows.append(("range min / median / max (m)", " / ".join(f"{v:.2f}" for v in summary["range_m"])))
    rows.append(("time span (s)", f"{summary['time_span_s']:.3f}"))
    if summary["scan_period_s"] is not None:
        rows.append(("scan period (s)", f"{summary['scan_period_s']:.3f}"))
    rows.append(("trajectory length (m)", f"{summary['trajectory_length_m']:.2f}"))
    rows.append(("attributes", ", ".join(summary["attributes"]) or "-"))
    for row in rows:
        table.add_row(*row)
    console.print(table)


@app.command("synth-world")
def synth_world(
    out: Path = typer.Option(..., "--out", "-o", help="Output log (`.npz`) with ground-truth `label` and `instance` per ray."),
    seed: int = typer.Option(11, help="World seed (layout, objects, noise)."),
    length: float = typer.Option(100.0, help="World length along the vehicle path (m)."),
    width: float = typer.Option(50.0, help="World width (m)."),
    spacing: float = typer.Option(1.5, help="Distance between scans along the path (m)."),
):
    """Generate a synthetic off-road world (terrain, trees and shrubs of leaf triangles, grass, rocks) and log a drive through it with a true sensor (beam divergence, mixed pixels, dropouts).

    Examples:

        mi-lidar synth-world --out train.npz --seed 11

        mi-lidar synth-world --out test.npz --seed 22 --length 120
    """
    from .hybrid.world import WorldSpec, make_world, path_poses, render_log

    with console.status("building the world and logging the drive"):
        world = make_world(seed, WorldSpec(length=length, width=width))
        log = render_log(world, path_poses(world, spacing), seed=seed)
        path = log.save(out)
    console.print(scan_summary(log, f"synthetic world (seed {seed})"))
    console.print(f"wrote {path}")


@app.command("fit-scene")
def fit_scene(
    log: Path = typer.Argument(..., help="Labeled log (`.npz`), e.g. from `mi-lidar synth-world`.", exists=True, dir_okay=False),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder for the scene XML, PLY assets and previews."),
    name: str = typer.Option("scene", help="Scene name (XML file stem)."),
):
    """Fit a hybrid geometric scene (ground triangles + vegetation ellipsoids with hit probabilities) to a log.

    Example:

        mi-lidar fit-scene train.npz --out fitted/
    """
    from .hybrid.commands import fit_scene as run

    try:
        xml = run(log, out, name=name)
    except (MiLidarError, ValueError) as exc:
        _fail(exc)
    console.print(f"wrote {xml}")


primitives_app = typer.Typer(help="The primitive library: labeled objects cut from fitted scenes.", no_args_is_help=True)
app.add_typer(primitives_app, name="primitives")


@primitives_app.command("extract")
def primitives_extract(
    log: Path = typer.Argument(..., help="Labeled log (`.npz`).", exists=True, dir_okay=False),
    library: Path = typer.Option(..., "--library", "-l", help="Library folder (created or extended)."),
):
    """Fit the log, cut it into labeled objects and store each as a primitive at the identity pose.

    Example:

        mi-lidar primitives extract train.npz --library lib/
    """
    from .hybrid.commands import primitives_extract as run

    try:
        lib = run(log, library)
    except (MiLidarError, ValueError) as exc:
        _fail(exc)
    console.print(f"{library}: {len(lib.primitives)} primitives")


@primitives_app.command("list")
def primitives_list(library: Path = typer.Argument(..., help="Library folder.", exists=True, file_okay=False)):
    """List the primitives of a library as a table.

    Example:

        mi-lidar primitives list lib/
    """
    from .hybrid.commands import primitives_list as run

    try:
        rows = run(library)
    except (MiLidarError, ValueError) as exc:
        _fail(exc)
    if not rows:
        console.print(f"{library}: no primitives")
        return
    table = Table(title=str(library), header_style="bold")
    for key in rows[0]:
        table.add_column(str(key))
    for row in rows:
        table.add_row(*(f"{v:.2f}" if isinstance(v, float) else str(v) for v in row.values()))
    console.print(table)


@primitives_app.command("show")
def primitives_show(
    library: Path = typer.Argument(..., help="Library folder.", exists=True, file_okay=False),
    out: Path = typer.Option(..., "--out", "-o", help="Output PNG."),
    per_class: int = typer.Option(4, help="Primitives shown per class."),
):
    """Draw primitives of every class into one PNG.

    Example:

        mi-lidar primitives show lib/ --out lib.png
    """
    from .hybrid.commands import primitives_show as run

    try:
        path = run(library, out, per_class=per_class)
    except (MiLidarError, ValueError) as exc:
        _fail(exc)
    console.print(f"wrote {path}")


@app.command()
def annotate(
    log: Path = typer.Argument(..., help="Labeled log (`.npz`).", exists=True, dir_okay=False),
    out: Path = typer.Option(..., "--out", "-o", help="Output annotation JSON (class, pose and box per object)."),
):
    """Write the annotation (class, pose, box per object) of a labeled log.

    Example:

        mi-lidar annotate test.npz --out test_annotation.json
    """
    from .hybrid.commands import annotate as run

    try:
        path = run(log, out)
    except (MiLidarError, ValueError) as exc:
        _fail(exc)
    console.print(f"wrote {path}")


@app.command()
def compose(
    annotation: Path = typer.Argument(..., help="Annotation JSON (from `mi-lidar annotate` or written by hand).", exists=True, dir_okay=False),
    library: Path = typer.Option(..., "--library", "-l", help="Primitive library folder.", exists=True, file_okay=False),
    out: Path = typer.Option(..., "--out", "-o", help="Output scene XML."),
):
    """Build a new scene from an annotation: per object, the primitive of its class with the closest box, placed at its pose.

    Example:

        mi-lidar compose test_annotation.json --library lib/ --out composed.xml
    """
    from .hybrid.commands import compose as run

    try:
        xml = run(annotation, library, out)
    except (MiLidarError, ValueError) as exc:
        _fail(exc)
    console.print(f"wrote {xml}")


def _vector(text: str, name: str) -> list[float]:
    values = [float(v) for v in text.split(",")]
    if len(values) != 3:
        raise typer.BadParameter(f"{name} needs three comma-separated numbers (m), e.g. 0,0,1.8; got {text!r}")
    return values


@app.command("camera-lidar")
def camera_lidar(
    scene: Path = typer.Argument(..., help="Scene XML with a `lidar` sensor (add emitters to light the camera).", exists=True, dir_okay=False),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder."),
    camera_from: str = typer.Option("0,0,1.8", "--from", help="Camera position x,y,z (m)."),
    camera_to: str = typer.Option("10,0,1.5", "--to", help="Point the camera looks at x,y,z (m)."),
    width: int = typer.Option(640, help="Image width (pixels)."),
    height: int = typer.Option(400, help="Image height (pixels)."),
    fov: float = typer.Option(70.0, help="Horizontal field of view (deg)."),
    spp: int = typer.Option(64, help="Camera samples per pixel."),
    seed: int = typer.Option(0, help="Random seed."),
):
    """Synthetic camera + Lidar data from one scene: image, scan, projection and calibration (KITTI-style).

    Writes `image.png` (sRGB), `image.exr` (linear), `points.ply` (world frame), `scan.npz`,
    `overlay.png` (Lidar returns over the image, coloured by depth) and `calib.json` (K, lidar_to_camera).

    Example:

        mi-lidar camera-lidar scenes_xml/urban_street.xml --out out/frame --from 0,0,1.8 --to 10,2,1.5
    """
    import json

    from .camera import PinholeCamera, camera_lidar_frame
    from .io import write_exr, write_ply
    from .io.preview import overlay_png, rgb_png
    from .scene import load_scene

    try:
        loaded = load_scene(scene)
        camera = PinholeCamera.look_at(_vector(camera_from, "--from"), _vector(camera_to, "--to"),
                                       width=width, height=height, fov_deg=fov)
        with console.status("rendering the camera image and the Lidar scan"):
            frame = camera_lidar_frame(loaded, camera, seed=seed, spp=spp)
        out.mkdir(parents=True, exist_ok=True)
        files = [
            rgb_png(out / "image.png", frame["image"]),
            write_exr(out / "image.exr", {c: frame["image"][..., i] for i, c in enumerate("RGB")}),
            write_ply(out / "points.ply", frame["points"].astype(np.float32)),
            frame["log"].save(out / "scan.npz"),
            overlay_png(out / "overlay.png", frame["image"], frame["uv"][frame["visible"]], frame["depth"][frame["visible"]],
                        title=f"{scene.name}: Lidar returns over the camera image"),
        ]
        calib = {"K": frame["K"].tolist(), "lidar_to_camera": frame["lidar_to_camera"].tolist(),
                 "camera_convention": "OpenCV (x right, y down, z forward)", "width": width, "height": height}
        (out / "calib.json").write_text(json.dumps(calib, indent=1))
    except (MiLidarError, ValueError) as exc:
        _fail(exc)
    console.print(f"{int(frame['visible'].sum()):,} of {len(frame['points']):,} Lidar returns fall in the image")
    for path in files + [out / "calib.json"]:
        console.print(f"wrote {path}")


@app.command("compare")
def compare_command(
    log: Path = typer.Argument(..., help="Measured log (any format `convert` reads).", exists=True),
    scene: Path = typer.Argument(..., help="Scene XML of the model (its sensor and integrator settings and effects).", exists=True, dir_okay=False),
    out: Path = typer.Option(..., "--out", "-o", help="Report folder: report.md/.html, PNG plots, residual image, residuals.ply."),
    seed: int = typer.Option(0, help="Seed of the simulated scan."),
):
    """Compare the model with a measured log ray by ray: NLL, range error, hit/miss F1, histogram match, and where it fails worst.

    Examples:

        mi-lidar compare room.npz scenes_xml/indoor_planar.xml --out reports/before
    """
    from .io import read_any
    from .loop import compare as run
    from .scene import load_scene

    try:
        with console.status("simulating the log's rays and comparing"):
            result = run(read_any(log), load_scene(scene), out=out, seed=seed)
    except (MiLidarError, ValueError) as exc:
        _fail(exc)
    head = result.headline
    console.print(f"NLL {head['nll']:.3f} nats/ray, hit/miss F1 {head['f1']:.3f}; worst: "
                  f"{result.worst[0]['breakdown']} {result.worst[0]['group']} ({result.worst[0]['nll']:.2f} nats/ray)")
    console.print(f"report: {out / 'report.html'}")


@app.command("diagnose")
def diagnose_command(
    log: Path = typer.Argument(..., help="Measured log (any format `convert` reads).", exists=True),
    scene: Path = typer.Argument(..., help="Scene XML of the current model.", exists=True, dir_okay=False),
    out: Path = typer.Option(..., "--out", "-o", help="Report folder."),
    as_json: bool = typer.Option(False, "--json", help="Print the ranking as JSON (for scripts)."),
    candidate: Optional[list[str]] = typer.Option(None, "--candidate", help="Only try these effects (repeatable); default: the whole catalog."),
    steps: int = typer.Option(120, help="Adam steps per candidate fit."),
):
    """Find the physical effect the model lacks: fit every candidate on a training split, rank by held-out gain with a likelihood-ratio / BIC test.

    Examples:

        mi-lidar diagnose room.npz scenes_xml/indoor_planar.xml --out reports/diagnosis

        mi-lidar diagnose room.npz scenes_xml/indoor_planar.xml --out d --json --candidate incidence_dropout --candidate outliers
    """
    import json

    from rich.progress import Progress

    from .io import read_any
    from .loop import diagnose as run
    from .scene import load_scene

    try:
        with Progress(console=console, transient=True) as bar:
            task = bar.add_task("diagnose", total=None)
            result = run(read_any(log), load_scene(scene), out=out, candidates=candidate or None, steps=steps,
                         progress=lambda i, n, label: bar.update(task, completed=i, total=n, description=label))
    except (MiLidarError, ValueError) as exc:
        _fail(exc)
    if as_json:
        typer.echo(json.dumps(result.ranking(), indent=1, default=float))
    else:
        console.print(result.summary)


from .calibration.commands import calibrate  # noqa: E402  (a Typer command defined with the calibration layer)

app.command(name="calibrate")(calibrate)


@app.command()
def demo(
    out: Path = typer.Option(Path("demo_out"), "--out", "-o", help="Output folder."),
    seed: int = typer.Option(0, help="Random seed."),
):
    """The main job of `make demo`: render the bundled off-road scene, then run the loop on a log with a hidden effect.

    Example:

        mi-lidar demo --out demo_out
    """
    from .loop.demo import run_demo

    render(DEFAULT_SCENE, out, seed=seed, pattern=None)
    console.rule("The loop: a log with a hidden effect, its diagnosis, the error before and after")
    run_demo(out=out / "loop", echo=console.print)
