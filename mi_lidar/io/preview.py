"""Quick-look PNG images of scans: range images, bird's-eye views, camera images and Lidar overlays.

Figures are drawn with matplotlib's object API on an Agg canvas, so no global backend is
changed and no display is needed; camera images and overlays, written once per dataset frame,
are drawn with numpy and Pillow directly (milliseconds instead of a figure's half second).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import ListedColormap
from matplotlib.figure import Figure
from matplotlib.patches import Patch
from matplotlib.ticker import MaxNLocator

from mi_lidar.core.atomic import atomic_path

MISS_COLOUR = "#ff00ff"
EMPTY_COLOUR = "#b0b0b0"
FIGURE_WIDTH_IN = 12.0
DPI = 110
ROW_HEIGHT_IN = 0.1
OVERLAY_WIDTH = 960  # pixels: overlays enlarge the camera image by a whole factor to about this width


def _save(figure: Figure, path: str | os.PathLike) -> Path:
    """Render ``figure`` to PNG at ``path`` atomically."""
    FigureCanvasAgg(figure)
    with atomic_path(path) as tmp:
        figure.savefig(tmp, format="png", dpi=DPI)
    return Path(path)


def range_image_png(
    path: str | os.PathLike,
    ranges: np.ndarray,
    title: str = "range image",
    hit: np.ndarray | None = None,
    valid: np.ndarray | None = None,
) -> Path:
    """Draw an (H, W) range image with a colour bar in metres, misses in magenta, empty cells grey.

    Rows are beams (top row = first beam), columns are firings. Rows are stretched so that thin
    images stay readable: a 16 x 1800 or 32 x 1024 image is drawn 12 inches wide, and each
    beam is about 11 pixels tall (0.1 inch per row, image height clipped to 1.5..8 inches).
    A planar scan (H beams x 1 firing) is drawn as a range profile over the beams instead, with
    misses as magenta ticks on the beam axis.

    Args:
        path: Destination ``.png``.
        ranges: (H, W) ranges (m); NaN marks a miss.
        title: Figure title.
        hit: Optional (H, W) bool; False marks a miss as well.
        valid: Optional (H, W) bool; False marks a cell the sensor did not fire (a partial
            frame), drawn grey and left out of the miss fraction.

    Returns:
        The destination path.
    """
    ranges = np.asarray(ranges, dtype=np.float64)
    if ranges.ndim != 2:
        raise ValueError(f"range_image_png: ranges have shape {ranges.shape}; expected (H, W)")
    miss = ~np.isfinite(ranges)
    if hit is not None:
        miss |= ~np.asarray(hit, dtype=bool)
    empty = np.zeros_like(miss) if valid is None else ~np.asarray(valid, dtype=bool)
    miss &= ~empty
    rows, cols = ranges.shape
    if cols == 1:
        return _profile_png(path, ranges[:, 0], miss[:, 0], empty[:, 0], title)
    image_height_in = float(np.clip(rows * ROW_HEIGHT_IN, 1.5, 8.0))
    figure = Figure(figsize=(FIGURE_WIDTH_IN, image_height_in + 1.4))
    axes = figure.add_subplot()
    cmap = colormaps["viridis"].with_extremes(bad=MISS_COLOUR)
    shown = np.ma.masked_array(ranges, mask=miss | empty)
    image = axes.imshow(shown, cmap=cmap, aspect="auto", interpolation="nearest")
    if empty.any():
        axes.imshow(
            np.ma.masked_array(np.ones_like(ranges), mask=~empty),
            cmap=ListedColormap([EMPTY_COLOUR]),
            aspect="auto",
            interpolation="nearest",
        )
    colour_bar = figure.colorbar(image, ax=axes, pad=0.01, fraction=0.04)
    colour_bar.set_label("range (m)")
    axes.set_xlabel("firing (column)")
    axes.set_ylabel("beam (row)")
    axes.yaxis.set_major_locator(MaxNLocator(integer=True))
    fired = miss.size - int(empty.sum())
    axes.set_title(f"{title}  ({rows} x {cols}, {miss.sum() / fired:.1%} misses)" if fired else title)
    handles = [Patch(color=MISS_COLOUR, label="miss (no return)")]
    if empty.any():
        handles.append(Patch(color=EMPTY_COLOUR, label="not fired (partial frame)"))
    axes.legend(handles=handles, loc="upper right", fontsize=8)
    figure.tight_layout()
    return _save(figure, path)


def _profile_png(path, ranges: np.ndarray, miss: np.ndarray, empty: np.ndarray, title: str) -> Path:
    """Range over beam index for a planar scan (one firing per beam); misses ticked in magenta."""
    figure = Figure(figsize=(FIGURE_WIDTH_IN, 4.0))
    axes = figure.add_subplot()
    beam = np.arange(len(ranges))
    shown = np.where(miss | empty, np.nan, ranges)
    axes.plot(beam, shown, ".", markersize=3, color=colormaps["viridis"](0.35), label="return")
    if miss.any():
        axes.plot(
            beam[miss],
            np.zeros(int(miss.sum())),
            "|",
            color=MISS_COLOUR,
            markersize=14,
            markeredgewidth=3,
            label="miss (no return)",
        )
    axes.set_xlabel("beam (bearing index)")
    axes.set_ylabel("range (m)")
    axes.set_ylim(bottom=0.0)
    axes.grid(alpha=0.3)
    fired = len(ranges) - int(empty.sum())
    axes.set_title(f"{title}  ({len(ranges)} beams x 1 firing, {miss.sum() / max(fired, 1):.1%} misses)")
    axes.legend(loc="upper right", fontsize=8)
    figure.tight_layout()
    return _save(figure, path)


FLAT_M = 0.01  # points whose heights span less than this (m) are drawn in one colour: a scale of nothing


def birds_eye_png(
    path: str | os.PathLike,
    points: np.ndarray,
    values: np.ndarray | None = None,
    title: str = "bird's-eye view",
    value_label: str = "value",
    categorical: bool = False,
) -> Path:
    """Draw points from above (x right, y up) with equal axes in metres.

    Args:
        path: Destination ``.png``.
        points: (N, 3) points (m); rows with a non-finite coordinate (misses) are skipped.
        values: Optional (N,) colour values; the height ``z`` is used when None, unless the points lie within
            :data:`FLAT_M` of one height (a planar scan): then one colour, the height in the title, no colour bar.
        title: Figure title.
        value_label: Colour bar label when ``values`` is given (the legend's entries' name when categorical).
        categorical: ``values`` are classes (labels): one colour each from a qualitative palette and a
            legend ``<value_label> <value> (<count>)``, instead of a colour scale.

    Returns:
        The destination path.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"birds_eye_png: points have shape {points.shape}; expected (N, 3)")
    colour = points[:, 2] if values is None else np.asarray(values, dtype=np.float64)
    if colour.shape != (len(points),):
        raise ValueError(f"birds_eye_png: values have shape {colour.shape}; expected ({len(points)},)")
    keep = np.isfinite(points).all(axis=1) & np.isfinite(colour)
    figure = Figure(figsize=(8.0, 7.0))
    axes = figure.add_subplot()
    if categorical and values is not None:
        classes = np.unique(colour[keep])
        palette = colormaps["tab10" if len(classes) <= 10 else "tab20"]
        for k, value in enumerate(classes):
            mine = keep & (colour == value)
            name = f"{value_label} {value:g} ({int(mine.sum()):,})"
            axes.scatter(
                points[mine, 0], points[mine, 1], s=1.0, color=palette(k % palette.N), linewidths=0, label=name
            )
        axes.legend(loc="upper right", fontsize=8, markerscale=6, framealpha=0.8)
    elif values is None and keep.any() and np.ptp(colour[keep]) < FLAT_M:
        axes.scatter(points[keep, 0], points[keep, 1], s=1.0, color="tab:blue", linewidths=0)
        title = f"{title}, all at z = {np.median(colour[keep]):.2f} m"
    else:
        scatter = axes.scatter(points[keep, 0], points[keep, 1], c=colour[keep], s=1.0, cmap="viridis", linewidths=0)
        colour_bar = figure.colorbar(scatter, ax=axes)
        colour_bar.set_label("height z (m)" if values is None else value_label)
    axes.set_aspect("equal", adjustable="datalim")
    axes.set_xlabel("x (m)")
    axes.set_ylabel("y (m)")
    axes.set_title(f"{title}  ({int(keep.sum()):,} points)")
    axes.grid(True, linewidth=0.3)
    figure.tight_layout()
    return _save(figure, path)


def _srgb(image: np.ndarray) -> np.ndarray:
    """Linear RGB (H, W, 3) -> display sRGB in [0, 1]."""
    linear = np.clip(np.asarray(image, dtype=np.float64), 0.0, 1.0)
    return np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * linear ** (1 / 2.4) - 0.055)


def rgb_png(path: str | os.PathLike, image: np.ndarray) -> Path:
    """Write a linear (H, W, 3) RGB image as an 8-bit sRGB PNG (RGB, no alpha) at its own resolution, atomically."""
    from PIL import Image

    pixels = np.round(_srgb(image) * 255.0).astype(np.uint8)
    with atomic_path(path) as tmp:
        Image.fromarray(pixels).save(tmp, format="PNG")
    return Path(path)


def overlay_png(
    path: str | os.PathLike, image: np.ndarray, uv: np.ndarray, depth: np.ndarray, title: str = "Lidar over camera"
) -> Path:
    """Draw Lidar returns over a linear RGB image, coloured by depth, with a title and a colour bar.

    Drawn with numpy and Pillow (a few milliseconds, so datasets can afford one per frame and camera):
    the image is enlarged by a whole factor to about :data:`OVERLAY_WIDTH` pixels (nearest
    neighbour), each return is a square dot of the ``turbo`` colour of its depth between the
    nearest and farthest return, nearer dots drawn over farther ones.

    Args:
        path: destination ``.png``.
        image: (H, W, 3) linear RGB.
        uv: (N, 2) pixel coordinates of the returns ((0, 0) is the top-left corner of the image).
        depth: (N,) depth along the optical axis, m.
        title: text above the image; the number of points is appended.
    """
    from PIL import Image, ImageDraw, ImageFont

    height, width = image.shape[:2]
    scale = max(1, round(OVERLAY_WIDTH / width))
    canvas = np.repeat(np.repeat(np.round(_srgb(image) * 255.0).astype(np.uint8), scale, 0), scale, 1)
    uv, depth = np.asarray(uv, np.float64).reshape(-1, 2), np.asarray(depth, np.float64).reshape(-1)
    low, high = (float(depth.min()), float(depth.max())) if len(depth) else (0.0, 1.0)
    turbo = (colormaps["turbo"](np.linspace(0, 1, 256))[:, :3] * 255).astype(np.uint8)
    order = np.argsort(-depth, kind="stable")  # far first: near dots end on top
    level = np.round(255 * (depth[order] - low) / max(high - low, 1e-9)).astype(int)
    centre = np.floor(uv[order] * scale).astype(int)
    dot = max(2, scale)
    for dy in range(dot):
        for dx in range(dot):
            x, y = centre[:, 0] + dx - dot // 2, centre[:, 1] + dy - dot // 2
            inside = (x >= 0) & (x < canvas.shape[1]) & (y >= 0) & (y < canvas.shape[0])
            canvas[y[inside], x[inside]] = turbo[level[inside]]
    font = ImageFont.load_default(size=14)
    top, bar, margin = 24, 16, 84
    page = Image.new("RGB", (canvas.shape[1] + bar + margin, canvas.shape[0] + top), "white")
    page.paste(Image.fromarray(canvas), (0, top))
    ramp = np.repeat(turbo[::-1][np.linspace(0, 255, canvas.shape[0]).astype(int)][:, None], bar, axis=1)
    page.paste(Image.fromarray(ramp), (canvas.shape[1] + 6, top))
    draw = ImageDraw.Draw(page)
    draw.text((4, 4), f"{title}  ({len(uv):,} points)", fill="black", font=font)
    right = canvas.shape[1] + bar + 10
    for fraction in np.linspace(0, 1, 5):
        y = top + (1 - fraction) * (canvas.shape[0] - 1)
        draw.text(
            (right, min(max(y - 7, top), page.height - 16)),
            f"{low + fraction * (high - low):.1f}",
            fill="black",
            font=font,
        )
    draw.text((right, 4), "depth (m)", fill="black", font=font)
    with atomic_path(path) as tmp:
        page.save(tmp, format="PNG")
    return Path(path)
