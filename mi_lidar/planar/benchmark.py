"""The real-log benchmark for any planar CARMEN log (``mi-lidar benchmark-planar``).

It runs the real-planar protocol (``docs/benchmark_planar.md``): the log is split (every ``test_every``-th scan
is a test scan), every beam is traced through its own leave-out map (:mod:`mi_lidar.planar.protocol`), the
baselines of :mod:`mi_lidar.planar.models` and mi-lidar's permeable map (:mod:`mi_lidar.planar.permeable`) are
fitted on training beams only, and every model is scored on the test beams by the one likelihood (1 cm bins, the
one floor) and sampled by the one sampler. Per model it reports the test and training NLL per beam (and its
split over hits and misses), the miss precision, recall and F1 (threshold 0.5, and a threshold tuned on training
beams), and the realism of one sampled scan: median and p90 |sampled - measured| range where both returned,
hit/miss F1 of the samples, and the histogram match (L1 distance between the CDFs of measured and sampled
ranges); and, from :data:`SAMPLED_SCANS` sampled scans (the first is that one), the CRPS per test beam (mean and
median, m; a no-return is the log's no-return value on both sides: :func:`~mi_lidar.core.metrics.crps`), a
paired measure that, unlike the one-draw errors, does not reward a model for sampling less spread than the
sensor. Beside the models, the same sample metrics of a reference, the measured test scans re-paired between
beams of like nominal range (:mod:`mi_lidar.planar.reference`): what a model that samples like the sensor
scores. Nothing is tuned to a particular log: the sensor's no-return value is detected from the log (or given),
and bandwidths are chosen on held-out training scans.
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mi_lidar.core.atomic import output_folder
from mi_lidar.core.densities.histogram import support_end
from mi_lidar.core.log import Log
from mi_lidar.core.metrics import metrics_of
from mi_lidar.core.params import choose_names
from mi_lidar.core.streams import scan_follows
from mi_lidar.planar import models as m
from mi_lidar.planar.beams import nominal_beams
from mi_lidar.planar.permeable import PermeableMap, fit_milidar
from mi_lidar.planar.protocol import PlanarData, PlanarProtocol, prepare
from mi_lidar.planar.reference import repaired_scans
from mi_lidar.planar.tails import short_share
from mi_lidar.planar.trace import OCCUPANCY_NAMES, PlanarTrace

MODELS = ("M0", "M1", "M2a", "M2b", "M3a", "M3b", "P-Reg", "NP-Reg", "mi-lidar")
SAMPLED_SCANS = 8  # sampled test scans per model for the CRPS (seeds seed, seed + 1, ...)
UNMAPPED_WARNING = 0.2  # above this share of test beams returning where their map has no wall, the map is too sparse
MAP_ERROR_WARNING = 0.15  # m: above this median |z - r| of the test returns, map error outweighs the sensor
# (ten SLAM-corrected logs measured 2026-11-26: 0.039-0.089 m; Intel with its odometry's poses: 0.235 m)
SAMPLE_KEYS = (  # the sample metrics the report keeps (:func:`~mi_lidar.core.metrics.metrics_of`)
    "range_error_median",
    "range_error_p90",
    "f1",
    "histogram_l1",
    "histogram_l1_draws",
    "histogram_l1_draws_se",
    "hit_rate_simulated",
    "crps_mean",
    "crps_mean_se",
    "crps_median",
)


def miss_scores(p_miss: np.ndarray, miss: np.ndarray, threshold: float) -> dict:
    """Precision, recall and F1 of predicting a miss where ``p_miss > threshold``."""
    predicted = p_miss > threshold
    tp, fp, fn = int(np.sum(predicted & miss)), int(np.sum(predicted & ~miss)), int(np.sum(~predicted & miss))
    precision = tp / (tp + fp) if tp + fp else 0.0
    recall = tp / (tp + fn) if tp + fn else 0.0
    return {
        "precision": precision,
        "recall": recall,
        "f1": 2 * precision * recall / (precision + recall) if precision + recall else 0.0,
    }


def tuned_threshold(p_miss: np.ndarray, miss: np.ndarray) -> float:
    """The miss threshold that maximises the miss F1 on (training) beams."""
    grid = np.unique(np.concatenate([[0.0], np.quantile(p_miss, np.linspace(0, 1, 201))]))
    f1 = [miss_scores(p_miss, miss, t)["f1"] for t in grid]
    return float(grid[int(np.argmax(f1))])


@dataclass
class ModelRow:
    """The benchmark's figures of one model (see the module docstring).

    Besides the figures: ``ll`` the test beams' log-likelihoods, ``sampled`` the first test scan it
    sampled (range, hit; the one the one-draw sample metrics pair with the measured scan), and
    ``beams`` what builds the ``(training beams, test beams)`` it was fitted and scored with
    (:attr:`engine`).
    """

    name: str
    test_nll: float
    train_nll: float
    nll_hits: float
    nll_misses: float
    miss_at_half: dict
    miss_tuned: dict
    threshold: float
    samples: dict
    seconds: float
    ll: np.ndarray = field(repr=False, default=None)
    sampled: tuple = field(repr=False, default=None)
    model: object = field(repr=False, default=None)
    beams: Callable[[], tuple] | None = field(repr=False, default=None)

    @property
    def engine(self) -> tuple:
        """``(training beams, test beams, model)``, to simulate more scans at the same beams
        (:func:`mi_lidar.apps.scans.planar_datasets`). Built on each call, not kept: mi-lidar's beams
        hold every segment of every beam seven times (its angular spread: the own trace, each
        neighbour's, each footprint's two) per stacked map, about 1.2 GB per map for 300,000 training beams."""
        return (*self.beams(), self.model)

    def to_json(self) -> dict:
        return {
            "model": self.name,
            "test_nll": self.test_nll,
            "train_nll": self.train_nll,
            "test_nll_hits": self.nll_hits,
            "test_nll_misses": self.nll_misses,
            "miss_at_0.5": self.miss_at_half,
            "miss_tuned": self.miss_tuned,
            "miss_threshold": self.threshold,
            "samples": {k: self.samples[k] for k in SAMPLE_KEYS},
            "fit_seconds": self.seconds,
        }


@dataclass
class PlanarBenchmark:
    """Result of :func:`run_planar_benchmark` (``settings``: what the learned models chose on the training scans;
    ``no_return``: the range (m) that stands for a no-return in the CRPS: the log's no-return value, or its
    largest reading + 1 m when it has none; ``reference``: the sample metrics of the measured test scans
    re-paired, :mod:`mi_lidar.planar.reference`, empty when the log has one test scan)."""

    source: str
    data: PlanarData
    rows: list[ModelRow]
    nominal: dict
    seconds: dict
    settings: dict = field(default_factory=dict)
    no_return: float = float("nan")
    reference: dict = field(default_factory=dict)

    def warnings(self) -> list[str]:
        """What makes this run's figures score the map more than the sensor, one sentence each (the CLI
        prints them, the report shows them)."""
        out = []
        unmapped, off = self.nominal["unmapped_returns"], self.nominal["median_abs_err"]
        if unmapped > UNMAPPED_WARNING:
            out.append(
                f"{unmapped:.0%} of the test beams returned where their leave-out map has no wall, so the figures "
                "score the map more than the sensor: give a longer log that passes the same places more often, or "
                "a smaller --radius or --window"
            )
        if np.unique(self.data.test.scan).size < 2:
            every = self.data.protocol.test_every
            out.append(
                f"the log has one test scan (every {every}-th scan is one), so there is no reference row (it re-pairs "
                f"beams between test scans) and the test figures rest on {self.data.test.n:,} beams of one scan: give "
                f"a log of {every + 1} scans or more (many more for figures that hold), or a smaller --test-every"
            )
        if not np.any(self.data.test.hit):
            out.append(
                "no test beam returned (every reading of the test scans is the no-return value), so the range "
                "figures (|err|, hist L1, the residual plot) are empty: check the no-return value (mi-lidar info "
                "shows it; --max-range sets it) and that the test scans hold returns"
            )
        if off > MAP_ERROR_WARNING:
            out.append(
                f"the test returns lie a median {off:.2f} m from their leave-out map's walls (SLAM-corrected logs: "
                "4-9 cm), so the figures score the map more than the sensor: check that the poses are "
                "SLAM-corrected (raw odometry drifts), and that the scene holds still"
            )
        return out

    @property
    def train_beams_in_log(self) -> int:
        """Beams of every training scan of the log (``data.train`` has fewer when the protocol thinned them)."""
        log = self.data.log
        every_scan = dataclasses.replace(self.data.protocol, train_beams=0)
        return every_scan.split(log.shape[0])[1].size * int(log.shape[1])

    def to_json(self) -> dict:
        log = self.data.log
        return {
            "log": self.source,
            "scans": int(log.shape[0]),
            "beams": int(log.shape[1]),
            "max_range_m": float(log.sensor.get("max_range_m", float("inf"))),
            "crps_no_return_m": self.no_return,
            "protocol": self.data.protocol.__dict__,
            "test_beams": self.data.test.n,
            "train_beams": self.data.train.n,
            "train_beams_in_log": self.train_beams_in_log,
            "nominal": self.nominal,
            "warnings": self.warnings(),
            "seconds": self.seconds,
            "settings": self.settings,
            "models": [r.to_json() for r in self.rows],
            "reference_repaired_sensor": {k: self.reference[k] for k in SAMPLE_KEYS if k in self.reference},
        }


PART_BEAMS = 100_000  # beams scored and sampled at once: mi-lidar's hold every segment seven times (1.2 GB per 300,000)


def scan_parts(scan: np.ndarray, beams: int = PART_BEAMS) -> list[np.ndarray]:
    """Beam indices of consecutive runs of whole scans of at most ``beams`` beams each (a longer scan is a
    part of its own); ``scan``: the scan index of every beam, each scan's beams together."""
    ends = np.r_[np.flatnonzero(scan[1:] != scan[:-1]) + 1, scan.size] if scan.size else np.zeros(0, np.int64)
    parts, start = [], 0
    for previous, end in zip(np.r_[0, ends[:-1]], ends):
        if end - start > beams and previous > start:
            parts.append(np.arange(start, previous))
            start = previous
    return parts + [np.arange(start, scan.size)] if scan.size else parts


def scores_in_parts(
    beams_of: Callable, trace: PlanarTrace, model, draws: int = 0, seed: int = 0, part_beams: int = PART_BEAMS
) -> tuple:
    """Scored log-likelihood (B,), P(miss) (B,) and ``draws`` sampled scans (ranges and hits, (draws, B)) of
    ``trace``'s beams under ``model``, seeds ``seed``, ``seed + 1``, ...

    ``beams_of(trace)`` builds the engine's beams; they are built and scored part by part (:func:`scan_parts`,
    ``part_beams`` at most) as rays of one set (:meth:`~mi_lidar.planar.beams.EngineBeams.numbered_from`, with
    the set's random streams), so the figures are those of the whole set at once, and the memory a part's: a
    long log's test beams (every ``test_every``-th scan, not thinned like the training beams) held
    3.6 GB at once (Freiburg building 079, 959 test scans of 360 beams).
    """
    follows = scan_follows(trace.scan, trace.beam)
    ll, p_miss, ranges, hits, streams = [], [], [], [], None
    for index in scan_parts(trace.scan, part_beams):
        part = beams_of(trace.take(index)).numbered_from(int(index[0]))
        ll.append(part.log_likelihood(model))
        p_miss.append(part.p_miss(model))
        streams = streams or [part.streams(seed + k, follows) for k in range(draws)]
        sampled = [part.sample(model, s) for s in streams]
        ranges.append(np.stack([z for z, _ in sampled]) if draws else np.zeros((0, index.size)))
        hits.append(np.stack([h for _, h in sampled]) if draws else np.zeros((0, index.size), bool))
        del part
    if not ll:
        return np.zeros(0), np.zeros(0), np.zeros((draws, 0)), np.zeros((draws, 0), bool)
    return np.concatenate(ll), np.concatenate(p_miss), np.concatenate(ranges, axis=1), np.concatenate(hits, axis=1)


def map_settings(fitted: PermeableMap, share: float) -> dict:
    """What was fitted of one of mi-lidar's maps, for the report: its share in the stack, its Beta priors and
    exponents per occupancy class, its angular spread."""
    return {
        "share": float(share),
        **{f"beta_prior_{name}": [float(a), float(b)] for name, a, b in zip(OCCUPANCY_NAMES, fitted.a, fitted.b)},
        **{
            f"{kind}_exponent_{name}": float(value)
            for kind, values in zip(("range", "counts", "incidence"), fitted.interception[2:])
            for name, value in zip(OCCUPANCY_NAMES, values)
        },
        "angular_share_per_neighbour": float(fitted.angular),
        "footprint_share_per_neighbour": float(fitted.footprint),
    }


def _row(
    name: str,
    beams_of: Callable[[PlanarTrace], object],
    model,
    data: PlanarData,
    seconds: float,
    seed: int,
    no_return: float,
) -> ModelRow:
    """The figures of ``model`` on the training and test beams ``beams_of(trace)`` builds (:func:`scores_in_parts`)."""
    ll_train, p_train, _, _ = scores_in_parts(beams_of, data.train, model)
    ll_test, p_test, ranges, hits = scores_in_parts(beams_of, data.test, model, SAMPLED_SCANS, seed)
    miss_test, miss_train = ~data.test.hit, ~data.train.hit
    threshold = tuned_threshold(p_train, miss_train)
    z, hit = ranges[0], hits[0]
    return ModelRow(
        name=name,
        test_nll=float(-ll_test.mean()),
        train_nll=float(-ll_train.mean()),
        nll_hits=float(-ll_test[~miss_test].mean()) if (~miss_test).any() else float("nan"),
        nll_misses=float(-ll_test[miss_test].mean()) if miss_test.any() else float("nan"),
        miss_at_half=miss_scores(p_test, miss_test, 0.5),
        miss_tuned=miss_scores(p_test, miss_test, threshold),
        threshold=threshold,
        samples=metrics_of(ll_test, data.test.z, data.test.hit, z, hit, draws=(ranges, hits), no_return=no_return),
        seconds=seconds,
        ll=ll_test,
        sampled=(z, hit),
        model=model,
        beams=lambda: (beams_of(data.train), beams_of(data.test)),
    )


def run_planar_benchmark(
    log: Log,
    source: str = "",
    protocol: PlanarProtocol | None = None,
    models: tuple[str, ...] = MODELS,
    seed: int = 0,
    progress=None,
) -> PlanarBenchmark:
    """Run the protocol on ``log`` (see the module docstring).

    Args:
        log: a planar log of N beams x 1 firing (:func:`mi_lidar.io.carmen.read_carmen`).
        source: its file, for the report.
        protocol: the protocol's settings (default: the protocol's).
        models: the models to fit and score (names of :data:`MODELS`, in any case, with ``-`` or ``_``).
        seed: seed of the first sampled scan (the others: ``seed + 1``, ...).
        progress: optional ``progress(done, total, label)``.
    """
    say = progress or (lambda done, total, label: None)
    models = choose_names(models, MODELS, "benchmark-planar: unknown models")
    start = time.perf_counter()
    data = prepare(log, protocol, progress=say)
    seconds = dict(data.seconds)
    z_max = float(log.sensor.get("max_range_m", float("inf")))
    if not np.isfinite(z_max):
        z_max = float(np.nanmax(log.ranges)) + 1.0
    train = nominal_beams(data.train)
    samples = m.samples_of(data.train)
    fitted, timing = {}, {}

    def fit(name: str, build):
        if name in models or (name == "NP-Reg" and "mi-lidar" in models):
            t0 = time.perf_counter()
            fitted[name] = build()
            timing[name] = time.perf_counter() - t0
            say(len(fitted), len(models), f"fitted {name}")

    fit("M0", lambda: m.fit_m0(train, samples, z_max))
    if {"M1", "M2a", "M2b"} & set(models):
        t0 = time.perf_counter()
        family = m.fit_beam_family(train, samples, z_max)
        for name in ("M1", "M2a", "M2b"):
            if name in models:
                fitted[name], timing[name] = family[name], (time.perf_counter() - t0) / 3
    if {"M3a", "M3b"} & set(models):
        for name, model in m.fit_histograms(samples, z_max).items():
            if name in models:
                fitted[name], timing[name] = model, 0.0
    settings = {}

    def learned(family: str):
        model, settings[family] = m.fit_learned(data.train, z_max, family)
        return model

    chosen = {}

    fit("P-Reg", lambda: learned("p_reg"))
    fit("NP-Reg", lambda: learned("np_reg"))
    rows = []
    for name in [n for n in MODELS if n in fitted and n in models]:
        rows.append(_row(name, nominal_beams, fitted[name], data, timing[name], seed, z_max))
    if "mi-lidar" in models:
        t0 = time.perf_counter()
        permeable = fit_milidar(data.train, z_max, settings["np_reg"])
        elapsed = time.perf_counter() - t0
        chosen["mi-lidar"] = {
            "maps": {kept.name: map_settings(kept, share) for kept, share in zip(permeable.maps, permeable.shares)},
            "held_out_nll": {name: round(score, 4) for name, score in permeable.held_out.items()},
            "beam_correlation": {"shared": permeable.correlation.shared, "rho": permeable.correlation.rho},
            "shared_errors_pit_lags": permeable.shared_errors,
        }
        say(len(models), len(models), "fitted mi-lidar")
        rows.append(_row("mi-lidar", permeable.beams, permeable.model, data, elapsed, seed, z_max))
    both = data.test.hit & np.isfinite(data.test.nominal)
    err = np.abs(data.test.z - data.test.nominal)[both]
    nominal = {
        "median_abs_err": float(np.median(err)) if err.size else float("nan"),
        "p90_abs_err": float(np.quantile(err, 0.9)) if err.size else float("nan"),
        "short": short_share(data.test.z, data.test.hit, data.test.nominal),
        "long": float(np.mean(both & (data.test.z > data.test.nominal + 0.5))),
        "measured_miss": float(np.mean(~data.test.hit)),
        "nominal_miss": float(np.mean(~np.isfinite(data.test.nominal))),
        "unmapped_returns": float(np.mean(data.test.hit & ~np.isfinite(data.test.nominal))),
        "incidence_known": float(np.mean(np.isfinite(data.test.incidence[np.isfinite(data.test.nominal)]))),
        "surface_incidence_known": float(np.mean(np.isfinite(data.test.seg_incidence[data.test.seg_occupied]))),
    }
    reference = {}  # re-paired between test scans: one test scan would be paired with itself, a perfect score
    if np.unique(data.test.scan).size > 1:
        ranges, hits = repaired_scans(data.test, SAMPLED_SCANS, seed)
        no_ll = np.full(data.test.n, np.nan)  # a reference, not a model: no likelihood
        reference = metrics_of(
            no_ll, data.test.z, data.test.hit, ranges[0], hits[0], draws=(ranges, hits), no_return=z_max
        )
    if "p_reg" in settings:
        h_r, h_d, escape = settings["p_reg"]
        chosen["P-Reg"] = {"h_range_m": h_r, "h_incidence_deg": h_d, "escape_law": escape}
    if "np_reg" in settings:
        h_r, h_i, u, reach, h_null = settings["np_reg"]
        chosen["NP-Reg"] = {
            "h_range_m": h_r,
            "h_incidence_deg": h_i,
            "h_no_return_m": h_null,
            "uniform_share": u,
            "support_end_m": support_end(m.samples_of(data.train), reach, z_max),
        }
    seconds["fit_and_score"] = time.perf_counter() - start - sum(data.seconds.values())
    seconds["total"] = time.perf_counter() - start
    return PlanarBenchmark(
        source=source,
        data=data,
        rows=rows,
        nominal=nominal,
        seconds=seconds,
        settings=chosen,
        no_return=z_max,
        reference=reference,
    )


def benchmark_file(
    path: str | Path,
    out: str | Path | None = None,
    max_range: float | None = None,
    protocol: PlanarProtocol | None = None,
    models: tuple[str, ...] = MODELS,
    progress=None,
    message: str | None = None,
) -> PlanarBenchmark:
    """Read a CARMEN log, run the benchmark, and write ``benchmark.json``, ``benchmark.html`` and PNGs to ``out``.

    The folder ``out`` is made first (:func:`~mi_lidar.core.atomic.output_folder`: a path that cannot be a
    folder fails before the run, and a failed run leaves no empty folder). ``message`` names the laser lines
    to read (:func:`~mi_lidar.io.carmen.read_carmen`; default: FLASER, else ROBOTLASER1).
    """
    from mi_lidar.io.dispatch import read_any
    from mi_lidar.planar.report import write_benchmark

    with output_folder(out) if out is not None else contextlib.nullcontext():
        log = read_any(path, formats=("carmen",), max_range=max_range, message=message)
        result = run_planar_benchmark(log, str(path), protocol, models, progress=progress)
        if out is not None:
            write_benchmark(result, Path(out))
    return result
