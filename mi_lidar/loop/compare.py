"""Compare a sensor model with a measured log, ray by ray (``mi-lidar compare``).

For every ray of the log the model is scored and simulated:

* NLL: the scored ``-log p(z | model)`` of the measured return (its 1 cm bin) or miss, nats, with the
  one floor of :func:`mi_lidar.core.likelihood.score`;
* range error: ``|z_measured - z_simulated|`` where both returned, m;
* hit/miss confusion: precision, recall and F1 of simulated returns against measured ones;
* histogram match: L1 distance between the CDFs of measured and simulated ranges, m;
* Chamfer distance between the measured and simulated point clouds in the world frame, m (overall only).

Each is broken down by nominal range, incidence angle, beam, azimuth, time, element type, label
and shape (taken from the first element along the ray), and the groups where the model fails
worst (largest excess NLL) lead the report. When the log carries intensities, their residuals
follow, by range, incidence, beam and label (:mod:`mi_lidar.loop.intensity_residuals`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import drjit as dr
import numpy as np

from mi_lidar.core.decimals import fixed
from mi_lidar.core.elements import ElementTable
from mi_lidar.core.log import Log
from mi_lidar.core.metrics import metrics_of
from mi_lidar.core.problem import Problem
from mi_lidar.core.rays import LogRays, world_rays
from mi_lidar.core.segment import ELLIPSOID
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.core.trace import next_intersection

BREAKDOWNS = ("range", "incidence", "beam", "azimuth", "time", "element_type", "label", "shape")
NO_ELEMENT_GROUP = "none"
# group labels that start with what they count
NAMED_GROUPS = ("beam ", "beams ", "label ", "shape ", "scan ", "scans ")
MAX_LISTED_GROUPS = 24  # a report lists a breakdown of more groups (a scanner's beams) in blocks of neighbours
BEAM_BLOCKS = 12  # blocks of neighbouring beams the report lists instead


@dataclass
class RayTable:
    """Per-ray results of a comparison (numpy arrays of length N).

    Attributes:
        ll: log-likelihood of the measurement, nats.
        measured, hit: measured range (m, NaN for a miss) and return flag.
        sim_range, sim_hit: one simulated range (m) and return flag.
        nominal, cos_incidence: of the first element along the ray (NaN / 0 where none).
        kind, label, shape: of the first element (-1 where none).
        beam, column, scan, azimuth: ray indices and sensor-frame azimuth (deg).
        on_surface: True for returns on a scene surface
            (:meth:`~mi_lidar.core.problem.Problem.near_surface`; None when not checked).
    """

    ll: np.ndarray
    measured: np.ndarray
    hit: np.ndarray
    sim_range: np.ndarray
    sim_hit: np.ndarray
    nominal: np.ndarray
    cos_incidence: np.ndarray
    kind: np.ndarray
    label: np.ndarray
    shape: np.ndarray
    beam: np.ndarray
    column: np.ndarray
    scan: np.ndarray
    azimuth: np.ndarray
    on_surface: np.ndarray | None = None


def first_elements(scene, table: ElementTable, problem: Problem, model: SensorModel) -> dict:
    """Nominal range, incidence cosine, kind, label and shape of the first element of each ray."""
    out = {k: [] for k in ("nominal", "cos_incidence", "kind", "label", "shape")}
    for first in range(0, problem.index.size, 1 << 20):
        batch, _, _ = problem.rays.batch(problem.index[first : first + (1 << 20)])
        batch = model.prepare_rays(batch)
        with dr.suspend_grad():
            si, valid, element = next_intersection(
                scene, table, batch.origin, batch.origin, batch.direction, model.max_range
            )
            seg = table.traced_segment(si, valid, element, batch.origin, batch.direction, model.range_sigma)
        ok = np.asarray(valid)
        out["nominal"].append(np.where(ok, np.asarray(seg.nominal), np.nan))
        out["cos_incidence"].append(np.where(ok, np.asarray(seg.cos_incidence), 0.0))
        for key in ("kind", "label", "shape"):
            out[key].append(np.where(ok, np.asarray(getattr(seg, key)).astype(np.int64), -1))
    return {k: np.concatenate(v) for k, v in out.items()}


def simulate_log_rays(
    scene, table: ElementTable, rays: LogRays, model: SensorModel, seed: int, index: np.ndarray | None = None
) -> tuple:
    """One simulated (range, hit) per ray ``index`` of the log (all when None), same ray ids as the log."""
    index = np.arange(rays.n) if index is None else np.asarray(index)
    ranges, hits = [], []
    for first in range(0, index.size, 1 << 21):
        batch, _, _ = rays.batch(index[first : first + (1 << 21)])
        out = model.simulate_rays(scene, table, batch, seed)
        ranges.append(np.asarray(out["range"]))
        hits.append(np.asarray(out["hit"]))
    return np.concatenate(ranges), np.concatenate(hits)


def ray_table(log: Log, scene, model: SensorModel, seed: int = 0) -> RayTable:
    """Score, simulate and describe every ray of ``log`` under ``model``."""
    rays = LogRays.from_log(log, scene=scene)
    problem = Problem.build(scene, rays)
    ll = problem.log_likelihood(model)
    sim_range, sim_hit = simulate_log_rays(scene, problem.table, rays, model, seed)
    first = first_elements(scene, problem.table, problem, model)
    scan = rays.scan if log.directions.shape[0] > 1 else np.zeros_like(rays.scan)
    d = log.directions[scan, rays.beam, rays.column]
    azimuth = np.degrees(np.arctan2(d[..., 1], d[..., 0]))
    return RayTable(
        ll=ll,
        measured=rays.measured,
        hit=rays.hit,
        sim_range=sim_range,
        sim_hit=sim_hit,
        beam=rays.beam,
        column=rays.column,
        scan=rays.scan,
        azimuth=azimuth,
        on_surface=problem.near_surface(model),
        **first,
    )


def metrics(t: RayTable, mask: np.ndarray | None = None) -> dict:
    """Observation losses of the rays ``mask`` (all when None): :func:`metrics_of` on the table's columns."""
    m = np.ones(t.ll.size, bool) if mask is None else mask
    return metrics_of(t.ll[m], t.measured[m], t.hit[m], t.sim_range[m], t.sim_hit[m])


def group_keys(t: RayTable, by: str) -> np.ndarray:
    """Group label of every ray for breakdown ``by`` (strings, sortable)."""
    if by == "range":
        edges = np.array([0, 1, 2, 5, 10, 20, 40, 80, 1e9])
        idx = np.digitize(np.nan_to_num(t.nominal, nan=-1), edges)
        names = [f"{edges[i]:g}-{edges[i + 1]:g} m" for i in range(7)] + ["80+ m"]  # was "80-1e+09 m"
        names = np.array([NO_ELEMENT_GROUP, *names, "far"])
        return names[np.where(np.isnan(t.nominal), 0, idx)]
    if by == "incidence":
        angle = np.degrees(np.arccos(np.clip(t.cos_incidence, 0, 1)))
        idx = np.minimum((angle // 15).astype(int), 5)
        names = np.array([f"{15 * i:02d}-{15 * i + 15:02d} deg" for i in range(6)])
        return np.where(t.kind < 0, NO_ELEMENT_GROUP, names[idx])
    if by == "beam":
        return np.char.add("beam ", np.char.zfill(t.beam.astype(str), 3))
    if by == "azimuth":
        idx = ((t.azimuth + 180) // 30).astype(int) % 12
        return np.array([f"{-180 + 30 * i:+04d}..{-150 + 30 * i:+04d} deg" for i in range(12)])[idx]
    if by == "time":  # ten runs of scans, named by their first and last scan: scans 0-90, ..., scans 819-909
        n = int(t.scan.max()) + 1
        size = max(1, -(-n // 10))
        first = t.scan // size * size
        last = np.minimum(first + size, n) - 1
        runs = np.char.add(np.char.add(np.char.add("scans ", first.astype(str)), "-"), last.astype(str))
        return np.where(first == last, np.char.add("scan ", first.astype(str)), runs)
    if by == "element_type":
        return np.where(t.kind < 0, NO_ELEMENT_GROUP, np.where(t.kind == ELLIPSOID, "ellipsoid", "surface"))
    if by == "label":
        return np.where(t.label < 0, NO_ELEMENT_GROUP, np.char.add("label ", t.label.astype(str)))
    return np.where(t.shape < 0, NO_ELEMENT_GROUP, np.char.add("shape ", t.shape.astype(str)))


def group_name(row: dict) -> str:
    """A breakdown group as a reader names it: ``label 2``, ``range 2-5 m``, ``incidence none``.

    Args:
        row: a row of :attr:`Comparison.worst` (its ``breakdown`` and ``group``); the breakdown's name
            is written once (the labels of the beam, label, shape and time groups already say it).
    """
    group = row["group"]
    return group if group.startswith(NAMED_GROUPS) else f"{row['breakdown'].replace('_', ' ')} {group}"


def group_order(key: str) -> tuple:
    """Sort key of a group label: by its leading number where it has one (``-30..+000 deg`` before
    ``+000..+030 deg``, ``2-5 m`` before ``10-20 m``), then as text; ``none`` last."""
    head = key.split(" ")[-1] if key.startswith(NAMED_GROUPS) else key.split(" ")[0]
    number = head.split("..")[0].split("-")[0] if not head.startswith("-") else "-" + head[1:].split("..")[0]
    number = number.removesuffix("+")  # the open last range group, 80+ m
    try:
        return (0, float(number), key)
    except ValueError:
        return (1, 0.0, key)


def breakdown(t: RayTable, by: str) -> list[dict]:
    """Metrics per group of breakdown ``by``, with each group's excess NLL (nats, total)."""
    keys = group_keys(t, by)
    return group_rows(t, keys, sorted(np.unique(keys), key=group_order))


def beam_blocks(t: RayTable, blocks: int = BEAM_BLOCKS) -> list[dict]:
    """The beam breakdown in at most ``blocks`` runs of neighbouring beams, for a report that cannot list every beam.

    Each row holds the metrics over all rays of its beams (as :func:`breakdown`) and ``beams``, how many
    beams it covers. Its group reads ``beams 0-14``; for a scanner whose every beam keeps one azimuth (a
    planar scanner, whose beam index is its bearing) the azimuths of its first and last beam follow:
    ``beams 0-14 (-90..-76 deg)``.

    Args:
        t: the rays.
        blocks: runs of beams at most; each holds ``ceil(beams / blocks)`` beams, the last what remains.
    """
    n = int(t.beam.max()) + 1
    size = -(-n // blocks)
    first = np.arange(0, n, size)
    last = np.minimum(first + size, n) - 1
    names = [f"beams {a}-{b}" for a, b in zip(first, last)]
    bearing = np.full(n, np.nan)
    bearing[t.beam] = t.azimuth  # one of each beam's azimuths
    turn = (t.azimuth - bearing[t.beam] + 180.0) % 360.0 - 180.0  # each ray's azimuth from its beam's, deg
    if np.all(np.abs(turn) < 0.5) and np.all(np.isfinite(bearing)):
        step = float(np.median(np.abs(np.diff(bearing)))) if n > 1 else 1.0
        digits = 0 if step > 0.95 else 1  # 0.5 deg beams: -75.0..-60.5, not -75..-60 and then -60..-46

        def angle(deg: float) -> str:
            return fixed(deg, digits, signed=True)

        names = [f"{name} ({angle(bearing[a])}..{angle(bearing[b])} deg)" for name, a, b in zip(names, first, last)]
    rows = group_rows(t, np.asarray(names)[t.beam // size], names)
    covered = dict(zip(names, (last - first + 1).tolist()))
    return [dict(row, beams=covered[row["group"]]) for row in rows]


def group_rows(t: RayTable, keys: np.ndarray, order: list[str]) -> list[dict]:
    """Metrics of the rays of each group in ``order`` (``keys``: each ray's group), with the group's excess NLL
    (nats, total) and median residual (m); a group of no rays is left out."""
    overall = -np.mean(t.ll)
    rows = []
    for key in order:
        m = keys == key
        if not m.any():
            continue
        row = {"group": str(key), **metrics(t, m)}
        row["excess_nll"] = (row["nll"] - overall) * row["rays"]
        row["residual_median"] = (
            float(np.nanmedian(t.measured[m & t.hit] - t.nominal[m & t.hit]))
            if np.any(m & t.hit & np.isfinite(t.nominal))
            else float("nan")
        )
        rows.append(row)
    return rows


def gain_groups(t: RayTable, before: np.ndarray, after: np.ndarray, most: int = 3) -> list[dict]:
    """Where a change of model gains most: the ``most`` groups, one per breakdown, of the largest NLL drop.

    Args:
        t: the rays (a breakdown with one group says nothing and is skipped).
        before, after: (N,) per-ray log-likelihoods of the two models (nats).
        most: groups returned at most.

    Returns:
        Rows ``breakdown``, ``group``, ``rays``, ``gain`` (nats, total), ``nll_before`` and ``nll_after``
        (nats per ray), best first; only groups of at least 2 % of the rays.
    """
    rows = []
    for by in BREAKDOWNS:
        keys = group_keys(t, by)
        groups = np.unique(keys)
        if len(groups) < 2:
            continue
        for key in groups:
            m = keys == key
            rows.append(
                {
                    "breakdown": by,
                    "group": str(key),
                    "rays": int(m.sum()),
                    "gain": float(np.sum(after[m] - before[m])),
                    "nll_before": float(-before[m].mean()),
                    "nll_after": float(-after[m].mean()),
                }
            )
    best = {}
    for row in sorted(rows, key=lambda r: -(r["nll_before"] - r["nll_after"])):
        if row["rays"] >= 0.02 * before.size and row["breakdown"] not in best:
            best[row["breakdown"]] = row
    return sorted(best.values(), key=lambda r: -(r["nll_before"] - r["nll_after"]))[:most]


@dataclass
class Comparison:
    """Result of :func:`compare`.

    Attributes:
        headline: overall metrics (see :func:`metrics`).
        breakdowns: breakdown name -> rows of per-group metrics.
        beam_blocks: the beam breakdown in blocks of neighbouring beams (:func:`beam_blocks`) when it has
            more than :data:`MAX_LISTED_GROUPS` beams, for the report's table; else empty.
        worst: the groups with the largest excess NLL across all breakdowns.
        table: the per-ray results.
        intensity: the intensity residuals
            (:class:`~mi_lidar.loop.intensity_residuals.IntensityResiduals`) when the log carries
            intensities, else None.
        files: written report files.
        warnings: what makes the figures doubtful (e.g. :func:`~mi_lidar.scene.sensor_check.scene_warnings`).
    """

    headline: dict
    breakdowns: dict
    worst: list
    table: RayTable = field(repr=False, default=None)
    intensity: object = field(repr=False, default=None)
    files: list = field(default_factory=list)
    warnings: list = field(default_factory=list)
    beam_blocks: list = field(default_factory=list)

    def to_json(self) -> dict:
        out = {"headline": self.headline, "breakdowns": self.breakdowns, "worst": self.worst, "warnings": self.warnings}
        out |= {"beam_blocks": self.beam_blocks} if self.beam_blocks else {}
        return out | ({"intensity": self.intensity.to_json()} if self.intensity is not None else {})


def same_draw_warnings(t, log_seed, seed: int) -> list[str]:
    """A warning when the sampled scan is the log itself, ray for ray (an empty list otherwise).

    It is when the log was simulated by this very model with this seed: every realism figure is then
    0 (or F1 1) by construction and says nothing of the model.

    Args:
        t: the ray table (:func:`ray_table`).
        log_seed: the seed the log records having been simulated with (None for a measured log).
        seed: the seed compare sampled with.
    """
    if t.hit.size == 0 or not np.array_equal(t.hit, t.sim_hit):
        return []
    if not np.allclose(t.measured[t.hit], t.sim_range[t.hit], rtol=0.0, atol=1e-6):
        return []
    recorded = f" (the log records seed {log_seed})" if log_seed is not None else ""
    return [
        f"the sampled scan equals the log ray for ray: the log was simulated by this model with seed {seed}"
        f"{recorded}, so the sample figures are perfect by construction; compare with another --seed, or a "
        "log that holds something the model lacks"
    ]


def compare(
    log: Log,
    scene,
    model: SensorModel | None = None,
    out: str | Path | None = None,
    seed: int = 0,
    title: str = "Model vs measurements",
    force: bool = False,
) -> Comparison:
    """Compare ``model`` with ``log`` in ``scene`` ray by ray and optionally write a report.

    Args:
        log: measured log.
        scene: loaded Mitsuba scene or scene XML path.
        model: sensor model (default: the scene's sensor and integrator settings).
        out: report folder (PNG plots, residual range image, residual PLY, report.md/.html,
            comparison.json, and intensity_residuals.png when the log carries intensities); nothing
            is written when None.
        seed: simulation seed.
        title: report title.
        force: compare even when the log's sensor does not match the scene's.

    Returns:
        The :class:`Comparison`.

    Raises:
        SensorMismatchError: the log was recorded by another sensor than the scene's
            (:func:`~mi_lidar.scene.sensor_check.check_log_sensor`).
    """
    from mi_lidar.scene.loading import scene_sensor_model
    from mi_lidar.scene.sensor_check import log_scene, scene_warnings

    scene = log_scene(log, scene, force)
    model = model or scene_sensor_model(scene)[0]
    t = ray_table(log, scene, model, seed)
    origins, directions = world_rays(log, t.scan, t.beam, t.column)
    headline = metrics_of(t.ll, t.measured, t.hit, t.sim_range, t.sim_hit, origins, directions)
    result = Comparison(headline=headline, breakdowns={b: breakdown(t, b) for b in BREAKDOWNS}, worst=[], table=t)
    if len(result.breakdowns["beam"]) > MAX_LISTED_GROUPS:
        result.beam_blocks = beam_blocks(t)
    result.warnings = scene_warnings(t.on_surface, t.hit) + same_draw_warnings(t, log.sensor.get("seed"), seed)
    groups = [
        dict(row, breakdown=b) for b, rows in result.breakdowns.items() if b != "beam" or len(rows) > 1 for row in rows
    ]
    result.worst = sorted(groups, key=lambda r: -r["excess_nll"])[:8]
    from mi_lidar.loop.intensity_residuals import intensity_residuals

    result.intensity = intensity_residuals(log, scene, model, seed=seed)
    if out is not None:
        from mi_lidar.loop.report import write_comparison

        result.files = write_comparison(result, log, Path(out), title, model)
    return result
