"""An independent numpy planar world for the planar benchmark's tests: a room, a pillar, a glass pane.

The room is 12 m x 8 m (walls at x = 0, 12 and y = 0, 8), with a 1 m square pillar at (6, 4) and a
glass pane from (3, 6) to (3, 8) that returns a beam with probability ``glass_p`` (else it passes
on). A robot drives an ellipse around the pillar; the scanner has ``beams`` bearings over 180
degrees (the CARMEN angle rule), Gaussian range noise ``sigma`` and a no-return value ``max_range``.
The log is written as CARMEN ``FLASER`` text so the tests read it through the real reader.
"""

from __future__ import annotations

import numpy as np

from mi_lidar.io.carmen import beam_angles


def pillar(x: float, y: float, side: float = 1.0) -> np.ndarray:
    """(4, 4) wall segments (x0, y0, x1, y1; m) of a square pillar with its lower-left corner at (x, y)."""
    corners = np.array([[x, y], [x + side, y], [x + side, y + side], [x, y + side]], float)
    return np.concatenate([corners, np.roll(corners, -1, axis=0)], axis=1)


WALLS = np.concatenate(
    [np.array([[0, 0, 12, 0], [12, 0, 12, 8], [12, 8, 0, 8], [0, 8, 0, 0]], float), pillar(5.5, 3.5)]
)
GLASS = np.array([[3.0, 6.0, 3.0, 8.0]])


def cast(origin: np.ndarray, direction: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Distance (m) along each (N, 2) ray to each of (M, 4) segments; inf where missed. Shape (N, M)."""
    p, q = segments[:, :2], segments[:, 2:] - segments[:, :2]
    w = p[None] - origin[:, None]
    denom = direction[:, None, 0] * q[None, :, 1] - direction[:, None, 1] * q[None, :, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[..., 0] * q[None, :, 1] - w[..., 1] * q[None, :, 0]) / denom
        s = (w[..., 0] * direction[:, None, 1] - w[..., 1] * direction[:, None, 0]) / denom
    ok = (np.abs(denom) > 1e-12) & (t > 1e-6) & (s >= 0) & (s <= 1)
    return np.where(ok, t, np.inf)


def poses(scans: int) -> np.ndarray:
    """(S, 3) x, y, heading of the robot on its loop (two turns of an ellipse around the pillar)."""
    a = np.linspace(0, 4 * np.pi, scans, endpoint=False)
    x, y = 6 + 3.8 * np.cos(a), 4 + 2.3 * np.sin(a)
    return np.stack([x, y, a + np.pi / 2], axis=1)


def room_readings(scans: int, beams: int, sigma: float, glass_p: float, max_range: float, seed: int) -> np.ndarray:
    """(S, beams) readings (m); ``max_range`` where nothing returned or the return is beyond it."""
    rng = np.random.default_rng(seed)
    out = np.empty((scans, beams))
    for s, (x, y, heading) in enumerate(poses(scans)):
        angle = heading + beam_angles(beams)
        direction = np.stack([np.cos(angle), np.sin(angle)], axis=1)
        origin = np.repeat([[x, y]], beams, axis=0)
        wall = cast(origin, direction, WALLS).min(axis=1)
        glass = cast(origin, direction, GLASS)[:, 0]
        returned_glass = (glass < wall) & (rng.random(beams) < glass_p)
        z = np.where(returned_glass, glass, wall) + rng.normal(0.0, sigma, beams)
        out[s] = np.where(np.isfinite(z) & (z < max_range), z, max_range)
    return out


def room_log_text(
    scans: int = 60, beams: int = 181, sigma: float = 0.02, glass_p: float = 0.3, max_range: float = 50.0, seed: int = 0
) -> str:
    """The CARMEN text of a drive through the room (one FLASER line per scan, 0.2 s apart)."""
    return flaser_text(poses(scans), room_readings(scans, beams, sigma, glass_p, max_range, seed), "mi-lidar test room")


def flaser_text(poses: np.ndarray, readings: np.ndarray, title: str) -> str:
    """CARMEN text of (S, 3) poses (x, y, heading) and (S, beams) readings (m), one FLASER line per scan 0.2 s apart."""
    lines = [f"# {title}"]
    for s, ((x, y, heading), ranges) in enumerate(zip(poses, readings)):
        t = 100.0 + 0.2 * s
        pose = f"{x:.4f} {y:.4f} {heading:.5f}"
        lines.append(f"FLASER {len(ranges)} {' '.join(f'{r:.3f}' for r in ranges)} {pose} {pose} {t:.3f} host {t:.3f}")
    return "\n".join(lines) + "\n"
