"""Derive a CARMEN log from another, to check that the planar benchmark runs unchanged on other sensors.

    python tools/derive_carmen.py IN.log.gz OUT.log.gz [--every K] [--beams N] [--clip C]

* ``--every K``: keep every K-th scan (a sparser log);
* ``--beams N``: resample each scan to N beams over the same 180 degrees (181 and 361 use the
  inclusive CARMEN angle rule), by linear interpolation of the ranges in angle; a new beam between a
  return and a no-return is a no-return;
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


def derive(lines: list[str], every: int, beams: int | None, clip: float | None, no_return: float) -> list[str]:
    """The FLASER lines of the derived log (other lines are dropped)."""
    out, index = [], 0
    for line in lines:
        tokens = line.split()
        if not tokens or tokens[0] != "FLASER":
            continue
        keep = index % every == 0
        index += 1
        if not keep:
            continue
        n = int(tokens[1])
        ranges = np.array(tokens[2 : 2 + n], dtype=np.float64)
        rest = tokens[2 + n :]
        miss = ranges >= no_return - 0.015
        if beams is not None and beams != n:
            old, new = beam_angles(n), beam_angles(beams)
            values = np.interp(new, old, np.where(miss, 0.0, ranges))
            missing = np.interp(new, old, miss.astype(float)) > 0.0
            ranges, miss, n = np.where(missing, no_return, values), missing, beams
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
    parser.add_argument("--no-return", type=float, default=81.83, help="the source's no-return value (m)")
    args = parser.parse_args()
    raw = args.source.read_bytes()
    text = gzip.decompress(raw).decode() if raw[:2] == b"\x1f\x8b" else raw.decode()
    lines = derive(text.splitlines(), args.every, args.beams, args.clip, args.no_return)
    data = ("\n".join(lines) + "\n").encode()
    args.target.write_bytes(gzip.compress(data) if args.target.suffix == ".gz" else data)
    print(f"wrote {args.target}: {len(lines)} scans")


if __name__ == "__main__":
    main()
