"""Derive a CARMEN log from another, to check that the planar benchmark runs unchanged on other sensors.

    python tools/derive_carmen.py IN.log.gz OUT.log.gz [--every K] [--scans A:B] [--beams N]
        [--resample linear|nearest] [--noise S] [--clip C] [--seed N]

* ``--every K``: keep every K-th scan (a sparser log);
* ``--scans A:B``: keep only the scans A to B-1 of the source (a part of the trajectory), before ``--every``;
* ``--beams N``: resample each scan to N beams over the same 180 degrees (181 and 361 use the
  inclusive CARMEN angle rule); ``--resample linear`` (default) interpolates the ranges in angle (a
  new beam between a return and a no-return is a no-return; between two walls it lands in between,
  as a mixed pixel would), ``nearest`` copies the nearest source beam (no invented ranges);
* ``--noise S``: add Gaussian noise of S metres to every return (seeded by ``--seed``);
* ``--clip C``: a scanner that clips at C metres: readings at or beyond C, and no-returns, become C.

Poses, odometry and timestamps are kept. The output is gzip-compressed when its name ends in ``.gz``.
"""

from __future__ import annotations

import argparse
import gzip
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mi_lidar.io.carmen import beam_angles  # noqa: E402


def derive(
    lines: list[str],
    every: int,
    beams: int | None,
    clip: float | None,
    no_return: float,
    scans: tuple[int, int | None] = (0, None),
    resample: str = "linear",
    noise: float = 0.0,
    seed: int = 0,
) -> list[str]:
    """The FLASER lines of the derived log (other lines are dropped)."""
    rng = np.random.default_rng(seed)
    flaser = [line for line in lines if line.split()[:1] == ["FLASER"]]
    out = []
    for index, line in enumerate(flaser[scans[0] : scans[1]]):
        if index % every:
            continue
        tokens = line.split()
        n = int(tokens[1])
        ranges = np.array(tokens[2 : 2 + n], dtype=np.float64)
        rest = tokens[2 + n :]
        miss = ranges >= no_return - 0.015
        if beams is not None and beams != n:
            old, new = beam_angles(n), beam_angles(beams)
            if resample == "nearest":
                nearest = np.clip(np.round(np.interp(new, old, np.arange(n))).astype(int), 0, n - 1)
                ranges, miss = ranges[nearest], miss[nearest]
            else:
                values = np.interp(new, old, np.where(miss, 0.0, ranges))
                missing = np.interp(new, old, miss.astype(float)) > 0.0
                ranges, miss = np.where(missing, no_return, values), missing
            n = beams
        if noise > 0:
            ranges = np.where(miss, ranges, np.maximum(ranges + rng.normal(0.0, noise, n), 0.01))
        if clip is not None:
            ranges = np.where(miss | (ranges >= clip), clip, ranges)
        out.append(" ".join(["FLASER", str(n)] + [f"{r:.2f}" for r in ranges] + rest))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("source", type=Path)
    parser.add_argument("target", type=Path)
    parser.add_argument("--every", type=int, default=1)
    parser.add_argument("--beams", type=int, default=None)
    parser.add_argument("--clip", type=float, default=None)
    parser.add_argument("--scans", default=":", help="A:B, the source scans to keep (Python slice)")
    parser.add_argument("--resample", choices=("linear", "nearest"), default="linear")
    parser.add_argument("--noise", type=float, default=0.0, help="Gaussian range noise added to returns (m)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-return", type=float, default=81.83, help="the source's no-return value (m)")
    args = parser.parse_args()
    raw = args.source.read_bytes()
    text = gzip.decompress(raw).decode() if raw[:2] == b"\x1f\x8b" else raw.decode()
    first, _, last = args.scans.partition(":")
    span = (int(first or 0), int(last) if last else None)
    lines = derive(
        text.splitlines(), args.every, args.beams, args.clip, args.no_return, span, args.resample, args.noise, args.seed
    )
    data = ("\n".join(lines) + "\n").encode()
    args.target.write_bytes(gzip.compress(data) if args.target.suffix == ".gz" else data)
    print(f"wrote {args.target}: {len(lines)} scans")


if __name__ == "__main__":
    main()
