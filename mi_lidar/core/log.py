"""The scan/log data model and its on-disk format (``.npz``, format ``mi-lidar-log``, version 1).

A :class:`Log` holds ``S`` scans of one sensor whose rays form an ``H x W`` grid: ``H`` beams
(rows of the range image) by ``W`` firings (columns). A single scan is a log with ``S = 1``.

Conventions (every array is numpy):

========================  =====================  =========================================
field                     shape, dtype           meaning
========================  =====================  =========================================
``poses``                 (S, 4, 4) float64      sensor-to-world transform at sweep start
``directions``            (1|S, H, W, 3) float32 unit ray directions in the sensor frame
``origins``               (1|S, H, W, 3) float32 ray origins in the sensor frame (m)
``ranges``                (S, H, W) float32      measured range along the ray (m); NaN = miss
``hit``                   (S, H, W) bool         True where the sensor reported a return
``times``                 (S, H, W) float64      absolute timestamp of each ray (s)
``attributes[name]``      (S, H, W) any          per-ray extras (element_id, label, ...)
``sensor``                dict                   JSON-able metadata (name, pattern, ranges)
``source``                str or None            the file the log was read from (not saved)
========================  =====================  =========================================

A leading axis of 1 in ``directions``/``origins`` means that every scan shares the pattern.
Misses are explicit: ``hit`` is False and ``ranges`` is NaN; nothing is silently dropped.

On disk a log is one ``.npz`` archive holding the arrays above (attributes as ``attr/<name>``)
plus ``meta``: a JSON string with ``format``, ``version``, ``sensor`` and the attribute names (strict JSON: a
non-finite sensor value, such as ``max_range`` inf, is null there and listed to read back,
:func:`~mi_lidar.core.strict_json.dumps_exact`).
Files are written to a temporary name and renamed, so a crash never leaves half a file.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mi_lidar.core.atomic import atomic_write
from mi_lidar.core.errors import NUMPY_FILE_ERRORS, LogFormatError, numpy_file_problem
from mi_lidar.core.frames import MAX_COORDINATE_M
from mi_lidar.core.poses import validate_poses
from mi_lidar.core.strict_json import dumps_exact, loads_exact

FORMAT_NAME = "mi-lidar-log"
FORMAT_VERSION = 1
MAX_TIME_S = 1e11  # 3,000 years from 1970: a larger time is in ms, us or ns, or a misread number
UNIT_TOLERANCE = 1e-3  # |norm - 1| a ray direction may show (float32 storage, estimated miss directions)
PLANAR_SPREAD = 1e-3  # |z| of the beams' unit directions (sensor frame) below which a log is planar


@dataclass
class Log:
    """``S`` Lidar scans on an ``H x W`` (beams x firings) ray grid; see the module docstring."""

    poses: np.ndarray
    directions: np.ndarray
    ranges: np.ndarray
    hit: np.ndarray
    times: np.ndarray
    origins: np.ndarray | None = None
    attributes: dict[str, np.ndarray] = field(default_factory=dict)
    sensor: dict = field(default_factory=dict)
    source: str | None = field(default=None, compare=False)  # the file it was read from (None: made in memory)

    def __post_init__(self):
        self.poses = np.asarray(self.poses, dtype=np.float64)
        self.directions = np.asarray(self.directions, dtype=np.float32)
        self.ranges = np.asarray(self.ranges, dtype=np.float32)
        self.hit = np.asarray(self.hit, dtype=bool)
        self.times = np.asarray(self.times, dtype=np.float64)
        if self.directions.ndim == 3:
            self.directions = self.directions[None]
        if self.origins is None:
            self.origins = np.zeros((1,) + self.directions.shape[1:], dtype=np.float32)
        self.origins = np.asarray(self.origins, dtype=np.float32)
        if self.origins.ndim == 3:
            self.origins = self.origins[None]
        self.validate()

    # ------------------------------------------------------------------ shape
    @property
    def shape(self) -> tuple[int, int, int]:
        """``(S, H, W)``: scans, beams, firings."""
        return tuple(self.ranges.shape)

    @property
    def n_scans(self) -> int:
        return self.ranges.shape[0]

    @property
    def n_rays(self) -> int:
        return int(self.ranges.size)

    @property
    def is_planar(self) -> bool:
        """Whether every beam lies in the sensor's xy plane: the unit ray directions (sensor frame) have ``|z|`` below
        :data:`PLANAR_SPREAD` (a 2D scanner such as a SICK LMS; not a spinning 3D Lidar, nor one ring of it)."""
        return bool(np.nanmax(np.abs(self.directions[..., 2])) < PLANAR_SPREAD)

    def validate(self) -> None:
        """Raise :class:`LogFormatError` naming the first inconsistent field."""
        if self.ranges.ndim != 3:
            raise LogFormatError(f"ranges must have shape (S, H, W); got {self.ranges.shape}")
        s, h, w = self.ranges.shape
        expect = {
            "poses": (self.poses, (s, 4, 4)),
            "hit": (self.hit, (s, h, w)),
            "times": (self.times, (s, h, w)),
        }
        for name, (array, shape) in expect.items():
            if array.shape != shape:
                raise LogFormatError(f"{name} has shape {array.shape}; expected {shape} to match ranges")
        for name in ("directions", "origins"):
            array = getattr(self, name)
            if array.shape not in ((1, h, w, 3), (s, h, w, 3)):
                raise LogFormatError(f"{name} has shape {array.shape}; expected (1, {h}, {w}, 3) or ({s}, {h}, {w}, 3)")
        for name, array in self.attributes.items():
            if np.shape(array) != (s, h, w):
                raise LogFormatError(f"attribute {name!r} has shape {np.shape(array)}; expected {(s, h, w)}")
        if np.any(self.hit & ~np.isfinite(self.ranges)):
            raise LogFormatError("a ray flagged as hit has a non-finite range; set hit=False for misses")

    def check_values(self, source: str | os.PathLike = "log") -> None:
        """Refuse numbers no measurement has: a pose that is not a finite rigid transform, a non-finite time or
        origin, a time beyond :data:`MAX_TIME_S`, a ray direction that is not a finite unit vector, a negative range
        of a hit or one beyond :data:`~mi_lidar.core.frames.MAX_COORDINATE_M`.

        Shapes are :meth:`validate`'s; these are the values (one vectorized pass, the first bad ray named as
        ``[scan, beam, firing]``).

        Args:
            source: Name starting every message (usually the file).

        Raises:
            PoseError: a bad pose (index named).
            LogFormatError: any other bad value, named with its ray and value.
        """
        validate_poses(self.poses, source)
        norm = np.linalg.norm(self.directions, axis=-1)
        origins = np.asarray(self.origins)  # set by __post_init__
        checks = (
            ("time", self.times, ~np.isfinite(self.times), "s"),
            (
                "time",
                self.times,
                np.abs(self.times) > MAX_TIME_S,
                f"s, beyond {MAX_TIME_S:.0e} s from 1970 (ms, us or ns?)",
            ),
            ("origin", origins, ~np.isfinite(origins).all(axis=-1), "m"),
            ("direction length", norm, ~(np.abs(norm - 1.0) <= UNIT_TOLERANCE), "(a unit vector has 1)"),
            ("range of a hit", self.ranges, self.hit & (self.ranges < 0), "m (ranges are >= 0)"),
            (
                "range of a hit",
                self.ranges,
                self.hit & (self.ranges > MAX_COORDINATE_M),
                f"m, beyond {MAX_COORDINATE_M:.0e} m",
            ),
        )
        for name, values, bad, unit in checks:
            if bad.any():
                ray = np.unravel_index(int(np.argmax(bad)), bad.shape)
                value = values[ray]
                raise LogFormatError(
                    f"{source}: ray {list(map(int, ray))} has {name} {np.round(value, 6).tolist()} {unit}; the file "
                    "is damaged or was written wrongly: re-create it"
                )

    # --------------------------------------------------------------- helpers
    def scan(self, index: int) -> Log:
        """The ``index``-th scan as a one-scan log (arrays are views where possible)."""
        return self.select(slice(index, index + 1))

    def select(self, scans: slice | np.ndarray | list[int]) -> Log:
        """The scans ``scans`` as a log: a slice gives views where possible, indices give copies.

        Args:
            scans: A slice of scans, or (K,) scan indices.
        """
        pick = lambda a: a[scans] if a.shape[0] > 1 else a
        return Log(
            poses=self.poses[scans],
            directions=pick(self.directions),
            origins=pick(self.origins),
            ranges=self.ranges[scans],
            hit=self.hit[scans],
            times=self.times[scans],
            attributes={k: v[scans] for k, v in self.attributes.items()},
            sensor=dict(self.sensor),
            source=self.source,
        )

    def points_sensor(self) -> np.ndarray:
        """(S, H, W, 3) float32 return points in the sensor frame; NaN for misses."""
        r = np.where(self.hit, self.ranges, np.nan)[..., None]
        return (self.origins + r * self.directions).astype(np.float32)

    def points_world(self) -> np.ndarray:
        """(S, H, W, 3) float64 return points in the world frame; NaN for misses."""
        p = self.points_sensor().astype(np.float64)
        rot, trans = self.poses[:, None, None, :3, :3], self.poses[:, None, None, :3, 3]
        return np.einsum("shwij,shwj->shwi", np.broadcast_to(rot, p.shape[:3] + (3, 3)), p) + trans

    # ---------------------------------------------------------------- on disk
    def save(self, path: str | os.PathLike) -> Path:
        """Write the log to ``path`` (``.npz``) atomically and return the path."""
        path = Path(path)
        arrays: dict[str, Any] = {
            "poses": self.poses,
            "directions": self.directions,
            "origins": self.origins,
            "ranges": self.ranges,
            "hit": self.hit,
            "times": self.times,
        }
        arrays.update({f"attr/{k}": np.asarray(v) for k, v in self.attributes.items()})
        meta = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "sensor": self.sensor,
            "attributes": sorted(self.attributes),
        }
        arrays["meta"] = np.frombuffer(dumps_exact(meta).encode(), dtype=np.uint8)
        atomic_write(path, lambda stream: np.savez_compressed(stream, **arrays))
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> Log:
        """Read a log written by :meth:`save`.

        Raises:
            LogFormatError: any defect of the file, its shapes or its values (:meth:`check_values`).
            PoseError: a pose that is not a finite rigid transform.
        """
        path = Path(path)
        if not path.is_file():
            raise LogFormatError(f"{path}: no such log file")
        try:
            with np.load(path, allow_pickle=False) as data:
                arrays = {k: data[k] for k in data.files}
            meta = loads_exact(arrays.pop("meta").tobytes().decode()) if "meta" in arrays else None
        except NUMPY_FILE_ERRORS as exc:
            raise LogFormatError(
                f"{path}: not a readable mi-lidar log ({numpy_file_problem(exc)}); was it truncated? Re-create "
                "it with `mi-lidar simulate` or `mi-lidar convert`."
            ) from exc
        if meta is None:
            raise LogFormatError(f"{path}: missing 'meta' entry; this .npz is not an mi-lidar log")
        if not isinstance(meta, dict) or meta.get("format") != FORMAT_NAME:
            found = meta.get("format") if isinstance(meta, dict) else meta
            raise LogFormatError(f"{path}: format {found!r}; expected {FORMAT_NAME!r}")
        if meta.get("version") != FORMAT_VERSION:
            raise LogFormatError(
                f"{path}: log format version {meta.get('version')}; this mi-lidar reads version "
                f"{FORMAT_VERSION}. Upgrade mi-lidar or convert the file."
            )
        missing = [k for k in ("poses", "directions", "origins", "ranges", "hit", "times") if k not in arrays]
        if missing:
            raise LogFormatError(f"{path}: missing arrays {missing}")
        sensor = meta.get("sensor", {})
        if not isinstance(sensor, dict):
            raise LogFormatError(f"{path}: meta 'sensor' is a {type(sensor).__name__}; expected a JSON object")
        attributes = {k[len("attr/") :]: v for k, v in arrays.items() if k.startswith("attr/")}
        try:
            log = cls(
                poses=arrays["poses"],
                directions=arrays["directions"],
                origins=arrays["origins"],
                ranges=arrays["ranges"],
                hit=arrays["hit"],
                times=arrays["times"],
                attributes=attributes,
                sensor=sensor,
                source=str(path),
            )
        except LogFormatError as exc:
            raise LogFormatError(f"{path}: {exc}") from exc
        except (ValueError, TypeError) as exc:
            raise LogFormatError(f"{path}: an array has values of the wrong type ({exc})") from exc
        log.check_values(path)
        return log
