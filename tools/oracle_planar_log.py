"""Write a synthetic planar CARMEN log whose true sensor is one of the benchmark's own models (the oracle log).

    .venv/bin/python tools/oracle_planar_log.py SOURCE.log.gz OUTDIR [--truth M3b --truth M1 ...]
        [--score M0 --score NP-Reg ...] [--seed N]

For each ``--truth`` (a name of :data:`mi_lidar.planar.benchmark.MODELS`, default ``M3b``) the
model is fitted on SOURCE by the planar benchmark itself (:func:`~mi_lidar.planar.benchmark.run_planar_benchmark`:
training scans only, leave-out maps), then every beam of every scan, training and test, is drawn
from that fitted model at that beam's nominal state in its own leave-out map (the engine the
benchmark scores it with: :attr:`~mi_lidar.planar.benchmark.ModelRow.engine`). Ranges are written
at 1 cm as the source does, a no-return as the source's no-return value; a sampled return at or
below 0 m (a residual histogram's left tail at a short nominal range) is written as 0.01 m. Every
other line (header, ``PARAM``, ``ODOM``) and every other field of a ``FLASER`` line (poses,
odometry, timestamps, host) is kept. The log is ``OUTDIR/oracle-<truth>.log.gz``.

Beside it, ``OUTDIR/oracle-<truth>.json`` holds, under ``synthetic_test``, the NLL and the realism
(:func:`~mi_lidar.core.metrics.metrics_of`) on the synthetic test scans of every model fitted on
SOURCE (the truths and every ``--score`` model, default all), each at the generating beams (its own
engine on SOURCE's leave-out maps) with :data:`~mi_lidar.planar.benchmark.SAMPLED_SCANS` draws
whose seeds differ from the synthetic scans', and ``point``: the deterministic ray cast at the same
nominal ranges (a return at every nominal hit, a miss at every nominal miss). No model is refitted
and no map is rebuilt from the synthetic ranges, so the truth is exactly the sensor there: if it has
a worse one-draw p90 and F1 than M0, a criterion "sample metrics no worse than M0's" rejects the
true sensor (it does on Intel for truths M3b, M1 and mi-lidar: docs/loop_results.md). Then run the
benchmark on the log unchanged (it rebuilds the map from the synthetic scans, which blurs it, and
refits every model)::

    mi-lidar benchmark-planar OUTDIR/oracle-M3b.log.gz --out OUTDIR/bench-M3b

Outputs go to OUTDIR only (use /tmp: the source log stays out of the repository).
"""

from __future__ import annotations

import argparse
import dataclasses
import gzip
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.core.arrays import aligned
from mi_lidar.core.atomic import atomic_write
from mi_lidar.core.metrics import metrics_of
from mi_lidar.core.strict_json import write_json
from mi_lidar.io.carmen import read_carmen
from mi_lidar.planar.beams import AngularMixture, EngineBeams
from mi_lidar.planar.benchmark import MODELS, SAMPLED_SCANS, ModelRow, run_planar_benchmark

RESOLUTION = 0.01  # m: the source's range format (two decimals)


def with_measurements(beams: EngineBeams | AngularMixture, z: np.ndarray, hit: np.ndarray):
    """The same beams with measured ranges ``z`` (m; ignored where not ``hit``) and return flags ``hit``."""
    if isinstance(beams, AngularMixture):
        return dataclasses.replace(beams, parts=tuple(with_measurements(p, z, hit) for p in beams.parts))
    return dataclasses.replace(
        beams, z=mi.Float(aligned(np.where(hit, z, 0.0).astype(np.float32))), hit=mi.Bool(aligned(hit))
    )


def draw(beams, model, seed: int, no_return: float) -> tuple[np.ndarray, np.ndarray]:
    """One scan from ``model`` at ``beams`` as the sensor writes it: (range at 1 cm, m; return flag)."""
    z, hit = beams.sample(model, seed)
    z = np.maximum(np.round(np.nan_to_num(z) / RESOLUTION) * RESOLUTION, RESOLUTION)
    hit = hit & (z < no_return - 0.015)  # a draw on the no-return code is read as a no-return
    return np.where(hit, z, no_return), hit


def scored_against(row: ModelRow, z: np.ndarray, hit: np.ndarray, no_return: float, seed: int) -> dict:
    """NLL and realism of ``row``'s model at its test beams against synthetic test scans ``z``, ``hit``."""
    _, test, model = row.engine
    with dr.suspend_grad():
        ll = with_measurements(test, z, hit).log_likelihood(model)
    draws = [draw(test, model, seed + k, no_return) for k in range(SAMPLED_SCANS)]
    ranges, hits = np.stack([d[0] for d in draws]), np.stack([d[1] for d in draws])
    return metrics_of(ll, z, hit, ranges[0], hits[0], draws=(ranges, hits), no_return=no_return)


def point_metrics(nominal: np.ndarray, z: np.ndarray, hit: np.ndarray, no_return: float) -> dict:
    """Realism of the deterministic ray cast at ``nominal`` (m, NaN: miss) against ``z``, ``hit`` (no NLL)."""
    point_hit = np.isfinite(nominal)
    point = np.where(point_hit, nominal, no_return)
    draws = (np.broadcast_to(point, (2, point.size)), np.broadcast_to(point_hit, (2, point.size)))
    return metrics_of(np.full(z.size, np.nan), z, hit, point, point_hit, draws=draws, no_return=no_return)


def write_bytes(path: Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically."""
    return atomic_write(path, lambda f: f.write(data))


def substitute(lines: list[str], ranges: np.ndarray) -> list[str]:
    """``lines`` with the ranges of the ``s``-th ``FLASER`` line replaced by ``ranges[s]`` (m, written at 1 cm)."""
    out, s = [], 0
    for line in lines:
        tokens = line.split()
        if tokens[:1] == ["FLASER"]:
            n = int(tokens[1])
            line = " ".join(["FLASER", str(n)] + [f"{r:.2f}" for r in ranges[s]] + tokens[2 + n :])
            s += 1
        out.append(line)
    if s != ranges.shape[0]:
        raise ValueError(f"the source has {s} FLASER lines; {ranges.shape[0]} scans were drawn")
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("source", type=Path)
    parser.add_argument("out", type=Path, help="output folder (e.g. under /tmp)")
    parser.add_argument("--truth", action="append", choices=MODELS, help="the true sensor (repeatable; default M3b)")
    parser.add_argument("--score", action="append", choices=MODELS, help="models to score (repeatable; default all)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the fits' samples; the draws use seed + 1000 on")
    args = parser.parse_args()
    truths = tuple(args.truth or ["M3b"])
    scored = tuple(args.score or MODELS)
    log = read_carmen(args.source)
    no_return = float(log.sensor["max_range_m"])
    if not np.isfinite(no_return):
        raise SystemExit(f"{args.source}: no no-return value detected; the oracle log needs one")
    models = tuple(m for m in MODELS if m in truths + scored)
    result = run_planar_benchmark(
        log, str(args.source), models=models, seed=args.seed, progress=lambda d, n, label: print(label, flush=True)
    )
    raw = args.source.read_bytes()
    lines = (gzip.decompress(raw) if raw[:2] == b"\x1f\x8b" else raw).decode().splitlines()
    args.out.mkdir(parents=True, exist_ok=True)
    for row in (r for r in result.rows if r.name in truths):
        train, test, model = row.engine
        ranges = np.full(log.shape[:2], no_return)
        drawn = {}
        for name, beams, trace, seed in (
            ("train", train, result.data.train, args.seed + 1000),
            ("test", test, result.data.test, args.seed + 2000),
        ):
            drawn[name] = draw(beams, model, seed, no_return)
            ranges[trace.scan, trace.beam] = drawn[name][0]
        target = args.out / f"oracle-{row.name}.log.gz"
        write_bytes(target, gzip.compress(("\n".join(substitute(lines, ranges)) + "\n").encode()))
        report = {
            "source": str(args.source),
            "truth": row.name,
            "truth_fitted_on_source": row.to_json(),
            "no_return_m": no_return,
            "synthetic_test": {
                **{r.name: scored_against(r, *drawn["test"], no_return, args.seed + 3000) for r in result.rows},
                "point": point_metrics(result.data.test.nominal, *drawn["test"], no_return),
            },
        }
        write_json(args.out / f"oracle-{row.name}.json", report, default=float)
        print(f"wrote {target}: truth {row.name}")
        for name, m in report["synthetic_test"].items():
            figures = (m["nll"], m["range_error_median"], m["range_error_p90"], m["f1"], m["histogram_l1"])
            print(f"  {name:9s} NLL {figures[0]:.3f}  median / p90 {figures[1]:.3f} / {figures[2]:.2f}", end="")
            print(f"  F1 {figures[3]:.3f}  L1 {figures[4]:.3f}  CRPS {m['crps_mean']:.3f} / {m['crps_median']:.4f}")


if __name__ == "__main__":
    main()
