"""The sample metrics' reference: measured test scans re-paired between beams of like nominal range."""

from __future__ import annotations

import numpy as np

from mi_lidar.core.metrics import metrics_of
from mi_lidar.planar.reference import repaired_scans
from mi_lidar.planar.trace import SEGMENT_FIELDS, PlanarTrace


def trace_of(scan: np.ndarray, nominal: np.ndarray, z: np.ndarray) -> PlanarTrace:
    """Beams without segments (the reference reads measured and nominal ranges only)."""
    n = z.size
    return PlanarTrace(
        scan=scan,
        beam=np.arange(n) % 100,
        z=z,
        nominal=nominal,
        incidence=np.full(n, np.nan),
        seg_start=np.zeros(n + 1, np.int64),
        **{f: np.zeros(0) for f in SEGMENT_FIELDS},
    )


def sensor(nominal: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A sensor whose law depends on the nominal range only: 2 cm noise, 8 % returns 0.2-1.2 m short, 4 % no-returns."""
    z = nominal + rng.normal(0.0, 0.02, nominal.size)
    short = rng.random(nominal.size) < 0.08
    z[short] -= rng.uniform(0.2, 1.2, short.sum())
    z[rng.random(nominal.size) < 0.04] = np.nan
    return z


def test_every_beam_takes_another_scans_outcome_of_its_own_kind():
    rng = np.random.default_rng(3)
    scans, beams = 40, 100
    scan = np.repeat(np.arange(scans), beams)
    nominal = rng.uniform(1.0, 20.0, scan.size)
    nominal[rng.random(scan.size) < 0.1] = np.nan  # nominal misses
    # every scan writes its own residual (hits) or its own range (nominal misses): the source scan shows
    z = np.where(np.isfinite(nominal), nominal + 0.001 * scan, 50.0 + scan)
    ranges, hits = repaired_scans(trace_of(scan, nominal, z), draws=3, seed=0)
    assert ranges.shape == hits.shape == (3, scan.size) and hits.all()
    met = np.isfinite(nominal)
    source_of_hit = np.round((ranges[:, met] - nominal[met]) / 0.001).astype(int)  # residual moved, kept whole
    source_of_miss = np.round(ranges[:, ~met] - 50.0).astype(int)
    assert np.all((source_of_hit >= 0) & (source_of_hit < scans)), "a nominal hit took a nominal miss's outcome"
    assert np.all(np.isin(source_of_miss, scan[~met])), "a nominal miss took a nominal hit's outcome"
    assert np.all(source_of_hit != scan[met]) and np.all(source_of_miss != scan[~met])
    # partners are near in nominal range: 20 ranks either side among 3,600 hits over 19 m is about 0.2 m
    assert np.all(np.abs(ranges[:, met] - 0.001 * source_of_hit - nominal[met]) < 1e-9)
    # three draws pick different partners
    assert np.mean(ranges[0] != ranges[1]) > 0.9


def test_the_reference_scores_like_a_fresh_scan_of_the_sensor():
    """The one-draw figures of the re-paired scans match those of independent scans of the same sensor at
    the same beams (20,000 beams, seed 7, means over 4 draws of each; tolerances 5 % on p90 and median,
    0.003 on F1), and a model that never draws short returns or no-returns beats both on p90 and F1."""
    rng = np.random.default_rng(7)
    scan = np.repeat(np.arange(200), 100)
    nominal = rng.uniform(1.0, 20.0, scan.size)
    measured = sensor(nominal, rng)
    hit = np.isfinite(measured)
    no_ll = np.full(scan.size, np.nan)
    keys = ("range_error_p90", "range_error_median", "f1")

    def figures(draws: list[np.ndarray]) -> np.ndarray:
        return np.mean([[metrics_of(no_ll, measured, hit, z, np.isfinite(z))[k] for k in keys] for z in draws], 0)

    ranges, hits = repaired_scans(trace_of(scan, nominal, measured), draws=4, seed=1)
    reference = figures([np.where(h, r, np.nan) for r, h in zip(ranges, hits)])
    fresh = figures([sensor(nominal, rng) for _ in range(4)])
    narrow = figures([nominal + rng.normal(0.0, 0.02, scan.size)])
    np.testing.assert_allclose(reference[:2], fresh[:2], rtol=0.05)
    assert abs(reference[2] - fresh[2]) < 0.003, (reference, fresh)
    assert narrow[0] < 0.5 * fresh[0] and narrow[2] > fresh[2] + 0.01, (narrow, fresh)


def test_a_kind_held_by_one_scan_keeps_its_own_outcome():
    scan = np.array([0, 0, 0, 1, 1, 1])
    nominal = np.array([1.0, 2.0, np.nan, 1.5, 2.5, 3.0])  # the only nominal miss: no partner anywhere
    z = np.array([1.01, 2.02, 7.0, 1.53, 2.54, np.nan])
    ranges, hits = repaired_scans(trace_of(scan, nominal, z), draws=2, seed=0)
    np.testing.assert_array_equal(ranges[:, 2], [7.0, 7.0])
    met = np.isfinite(nominal)
    assert np.all(ranges[:, met][hits[:, met]] >= 0.0) and (~hits[:, met]).sum() > 0  # scan 1's no-return moves
