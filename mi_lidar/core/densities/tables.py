"""Learned densities on disk: one ``.npz`` per fitted sensor model, and the state grids they are tabulated on.

A learned density (P-Reg, NP-Reg, the binned beam and histogram baselines) is a set of numpy tables
indexed by a *state*: nominal range bin, incidence bin, beam and label. :class:`StateGrid` turns a
segment's features into a flat state index (Dr.Jit, per lane); :func:`save_density` writes the
tables with a JSON header (format ``mi-lidar-density``, version 1, the density's catalog name, its
scalar parameters and the grid) and :func:`load_density` reads them back into the right class.
Files are written atomically.
"""

from __future__ import annotations

import math
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.core.arrays import aligned
from mi_lidar.core.atomic import atomic_write
from mi_lidar.core.errors import NPZ_MEMBER_ERRORS, LogFormatError, ParameterError, numpy_file_problem
from mi_lidar.core.segment import incidence_deg
from mi_lidar.core.strict_json import dumps_exact, loads_exact

FORMAT_NAME = "mi-lidar-density"
FORMAT_VERSION = 1
PSEUDO_SAMPLES = 30.0  # a state group's estimates are shrunk to its parent's with this many samples' weight


@dataclass
class StateGrid:
    """Bins of the state a learned density conditions on.

    Attributes:
        range_edges: (R + 1,) nominal range bin edges, m (ranges beyond the last edge use the last bin).
        incidence_edges: (I + 1,) incidence angle bin edges, deg; an extra last bin holds segments
            whose incidence is unknown (NaN ``cos_incidence``). An empty list conditions on nothing.
        n_beams: beams conditioned on (1: beams pooled).
        n_labels: labels conditioned on (1: labels pooled).
    """

    range_edges: list = field(default_factory=lambda: [0.0, 1.0e9])
    incidence_edges: list = field(default_factory=list)
    n_beams: int = 1
    n_labels: int = 1

    def __post_init__(self):
        """Refuse a grid no density could be tabulated on (ParameterError naming the field)."""
        check_table("state grid", "range_edges", self.range_edges, increasing=True)
        if len(self.incidence_edges):
            check_table("state grid", "incidence_edges", self.incidence_edges, increasing=True)
        for name in ("n_beams", "n_labels"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ParameterError(f"state grid: {name}={value!r} must be an integer >= 1")

    @property
    def n_range(self) -> int:
        return len(self.range_edges) - 1

    @property
    def n_incidence(self) -> int:
        """Incidence bins, the unknown bin included (1 when the grid ignores incidence)."""
        return len(self.incidence_edges) if self.incidence_edges else 1

    @property
    def size(self) -> int:
        """Number of states."""
        return self.n_range * self.n_incidence * self.n_beams * self.n_labels

    @property
    def range_centres(self) -> np.ndarray:
        """(R,) centre of each range bin, m (the open last bin, or one past 1e6 m: its lower edge + 0.5 m)."""
        edges = np.asarray(self.range_edges, np.float64)
        upper = np.where(np.isfinite(edges[1:]) & (edges[1:] < 1e6), edges[1:], edges[:-1] + 1.0)
        return 0.5 * (edges[:-1] + upper)

    def state_ranges(self) -> np.ndarray:
        """(size,) the range bin centre of every state (m), in :meth:`index_np` order."""
        return self.range_centres[np.arange(self.size) % self.n_range]

    def index_np(
        self,
        nominal: np.ndarray,
        incidence_deg: np.ndarray,
        beam: np.ndarray | None = None,
        label: np.ndarray | None = None,
    ) -> np.ndarray:
        """Flat state index of each sample (numpy; ``incidence_deg`` NaN = unknown)."""
        r = np.clip(np.searchsorted(self.range_edges, nominal, side="right") - 1, 0, self.n_range - 1)
        if self.incidence_edges:
            i = np.clip(
                np.searchsorted(self.incidence_edges, incidence_deg, side="right") - 1, 0, len(self.incidence_edges) - 2
            )
            i = np.where(np.isnan(incidence_deg), self.n_incidence - 1, i)
        else:
            i = np.zeros_like(r)
        b = np.zeros_like(r) if beam is None or self.n_beams == 1 else np.minimum(beam, self.n_beams - 1)
        lab = np.zeros_like(r) if label is None or self.n_labels == 1 else np.minimum(label, self.n_labels - 1)
        return ((lab * self.n_beams + b) * self.n_incidence + i) * self.n_range + r

    def index(self, nominal: mi.Float, cos_incidence: mi.Float, beam: mi.UInt32, label: mi.UInt32) -> mi.UInt32:
        """Flat state index of each lane (Dr.Jit); NaN ``cos_incidence`` is the unknown incidence bin."""
        edges = mi.Float(aligned(np.asarray(self.range_edges, np.float32)))
        n_r = self.n_range
        r = dr.binary_search(0, n_r, lambda k: dr.gather(mi.Float, edges, k + 1) <= nominal)
        r = dr.minimum(r, n_r - 1)
        if self.incidence_edges:
            delta = incidence_deg(cos_incidence)
            i_edges = mi.Float(aligned(np.asarray(self.incidence_edges, np.float32)))
            n_i = len(self.incidence_edges) - 1
            i = dr.minimum(dr.binary_search(0, n_i, lambda k: dr.gather(mi.Float, i_edges, k + 1) <= delta), n_i - 1)
            i = dr.select(dr.isnan(cos_incidence), self.n_incidence - 1, i)
        else:
            i = dr.zeros(mi.UInt32, dr.width(nominal))
        b = dr.minimum(beam, self.n_beams - 1) if self.n_beams > 1 else 0
        lab = dr.minimum(label, self.n_labels - 1) if self.n_labels > 1 else 0
        return mi.UInt32(((lab * self.n_beams + b) * self.n_incidence + i) * n_r + r)


def check_table(
    owner: str, name: str, table, lower: float = -math.inf, upper: float = math.inf, increasing: bool = False
) -> None:
    """Refuse a table with values that are not finite or outside ``[lower, upper]``, or, with
    ``increasing``, bin edges or nodes that are not 1-D, at least two and strictly increasing.

    Raises:
        ParameterError: naming ``owner`` (the density or grid), the table and the first bad value.
    """
    values = np.asarray(table, np.float64)
    bad = ~np.isfinite(values) | (values < lower) | (values > upper)
    if bad.any():
        raise ParameterError(
            f"{owner}: table {name} holds {float(values[bad].flat[0])!r}; "
            f"its values must be finite and in [{lower}, {upper}]"
        )
    if increasing and (values.ndim != 1 or values.size < 2 or np.any(np.diff(values) <= 0)):
        raise ParameterError(f"{owner}: {name} {values.tolist()!r} must be at least 2 strictly increasing values")


def save_density(
    path: str | os.PathLike,
    name: str,
    params: dict,
    grid: StateGrid | None,
    arrays: dict[str, np.ndarray],
    notes: dict | None = None,
) -> Path:
    """Write a learned density (atomically).

    Args:
        path: destination ``.npz``.
        name: the density's catalog name.
        params: its scalar parameters and options (JSON-able).
        grid: its state grid (None when it has none).
        arrays: its tables.
        notes: free-form facts to keep (training log, bandwidths chosen, held-out NLL); non-finite numbers read
            back as written (the header is strict JSON, :func:`~mi_lidar.core.strict_json.dumps_exact`).
    """
    meta = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "name": name,
        "params": params,
        "grid": None if grid is None else asdict(grid),
        "notes": notes or {},
    }
    payload: dict[str, Any] = {f"table/{k}": np.asarray(v) for k, v in arrays.items()}
    payload["meta"] = np.frombuffer(dumps_exact(meta, default=float).encode(), dtype=np.uint8)
    return atomic_write(path, lambda stream: np.savez_compressed(stream, **payload))


def read_density(path: str | os.PathLike) -> tuple[dict, dict[str, np.ndarray]]:
    """``(meta, tables)`` of a density file; :class:`LogFormatError` naming the file when it is not one."""
    path = Path(path)
    if not path.is_file():
        raise LogFormatError(f"{path}: no such density file; write one with `mi-lidar fit-sensor`")
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = loads_exact(bytes(data["meta"]).decode())
            tables = {k.split("/", 1)[1]: np.asarray(data[k]) for k in data.files if k.startswith("table/")}
    except NPZ_MEMBER_ERRORS as exc:  # json's and unicode's errors are ValueErrors
        raise LogFormatError(
            f"{path}: not a mi-lidar density file ({numpy_file_problem(exc)}); write one with `mi-lidar fit-sensor`"
        ) from None
    if not isinstance(meta, dict):
        raise LogFormatError(f"{path}: the density file's header is not a mapping; write it with `mi-lidar fit-sensor`")
    if meta.get("format") != FORMAT_NAME or meta.get("version") != FORMAT_VERSION:
        raise LogFormatError(
            f"{path}: format {meta.get('format')!r} version {meta.get('version')!r}; expected "
            f"{FORMAT_NAME!r} version {FORMAT_VERSION}"
        )
    damaged = [k for k, v in tables.items() if v.dtype.kind not in "biuf" or not np.isfinite(v).all()]
    if damaged or not isinstance(meta.get("params"), dict) or not isinstance(meta.get("grid"), (dict, type(None))):
        what = (
            f"tables {damaged} hold non-numeric or non-finite values" if damaged else "its header lacks params or grid"
        )
        raise LogFormatError(f"{path}: damaged density file: {what}; fit it again with `mi-lidar fit-sensor`")
    return meta, tables


def load_density(path: str | os.PathLike, expected: str | None = None, **overrides):
    """The density saved in ``path`` (its class's ``from_tables``), optionally checking its name.

    Raises:
        LogFormatError: the file is missing, damaged or not a density file.
        ParameterError: a parameter, override or table out of its range (the message names the file).
    """
    from mi_lidar.core.densities.base import DENSITIES

    meta, tables = read_density(path)
    name = meta["name"]
    if expected is not None and name != expected:
        raise ParameterError(f"{path}: holds a {name!r} density, not {expected!r}; write {name}(file=...) instead")
    if name not in DENSITIES:
        raise ParameterError(f"{path}: density {name!r} is not in the catalog ({', '.join(sorted(DENSITIES))})")
    try:
        grid = None if meta["grid"] is None else StateGrid(**meta["grid"])
    except (TypeError, ParameterError) as exc:
        raise LogFormatError(f"{path}: damaged density file: {exc}; fit it again with `mi-lidar fit-sensor`") from None
    try:
        return DENSITIES[name].from_tables({**meta["params"], **overrides}, grid, tables)
    except TypeError as exc:  # a table the density does not know
        raise LogFormatError(f"{path}: damaged density file: {exc}; fit it again with `mi-lidar fit-sensor`") from None
    except ParameterError as exc:  # a parameter or table out of range: name the file too
        raise ParameterError(f"{path}: {exc}") from None
