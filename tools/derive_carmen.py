"""Derive a CARMEN log from another, to check that the planar benchmark runs unchanged on other sensors.

    python tools/derive_carmen.py IN.log.gz OUT.log.gz [--every K] [--scans A:B] [--beams N]
        [--resample linear|nearest] [--noise S] [--clip C] [--seed N] [--message FLASER|ROBOTLASER1]

* ``--every K``: keep every K-th scan (a sparser log);
* ``--scans A:B``: keep only the scans A to B-1 of the source (a part of the trajectory), before ``--every``;
* ``--beams N``: resample each scan to N beams over the same 180 degrees (181 and 361 use the
  inclusive CARMEN angle rule); ``--resample linear`` (default) interpolates the ranges in angle (a
  new beam between a return and a no-return is a no-return; between two walls it lands in between,
  as a mixed pixel would), ``nearest`` copies the nearest source beam (no invented ranges);
* ``--noise S``: add Gaussian noise of S metres to every return (seeded by ``--seed``);
* ``--clip C``: a scanner that clips at C metres: readings at or beyond C, and no-returns, become C;
* ``--message ROBOTLASER1``: write robot laser lines instead of FLASER lines (the same scans: start
  angle and angular resolution of the 180-degree fan to full float precision, the FLASER pose as the
  laser pose, the odometry as the robot pose, ``--no-return`` as the maximum range, no remissions,
  zero velocities), to check the ROBOTLASER1 path of ``read_carmen`` and the benchmark.

Poses, odometry and timestamps are kept. The output is gzip-compressed when its name ends in ``.gz``.
"""

from __future__ import annotations

import argparse
import gzip
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mi_lidar.core.atomic import atomic_write  # noqa: E402
from mi_lidar.core.errors import LogFormatError  # noqa: E402
from mi_lidar.io.carmen import beam_angles, beam_step, parse_message  # noqa: E402
from mi_lidar.io.text import text_lines  # noqa: E402


def flaser_tokens(lines: list[str]) -> list[list[str]]:
    """The tokens of every FLASER line, parsed as ``read_carmen`` parses them (LogFormatError naming the line)."""
    out = []
    for number, line in enumerate(lines, start=1):
        tokens = line.split()
        if tokens[:1] != ["FLASER"]:
            continue
        values = parse_message(tokens, number)
        if not np.isfinite(values).all():
            bad = tokens[2 + int(np.argmin(np.isfinite(values)))]
            raise LogFormatError(f"line {number}: FLASER value {bad!r} is not finite: repair or delete the line")
        out.append(tokens)
    return out


def robot_laser_line(ranges: list[str], rest: list[str], no_return: float) -> str:
    """The ROBOTLASER1 line of a FLASER scan: its ``ranges`` (formatted, m) and ``rest`` (the tokens after them:
    laser pose, odometry, timestamp, host and logger timestamp)."""
    n = len(ranges)
    step = beam_step(n)
    angles = (repr(-np.pi / 2), repr(step * (n - 1)), repr(step))  # start_angle, field_of_view, angular_resolution
    config = ["0", *angles, f"{no_return:g}", "0.01", "0", str(n)]
    return " ".join(["ROBOTLASER1", *config, *ranges, "0", *rest[:6], "0 0 0 0 0", *rest[6:]])


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
    message: str = "FLASER",
) -> list[str]:
    """The ``message`` (FLASER or ROBOTLASER1) lines of the derived log (other lines are dropped)."""
    rng = np.random.default_rng(seed)
    out = []
    for index, tokens in enumerate(flaser_tokens(lines)[scans[0] : scans[1]]):
        if index % every:
            continue
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
        text = [f"{r:.2f}" for r in ranges]
        out.append(
            robot_laser_line(text, rest, no_return)
            if message == "ROBOTLASER1"
            else " ".join(["FLASER", str(n), *text, *rest])
        )
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
    parser.add_argument("--message", choices=("FLASER", "ROBOTLASER1"), default="FLASER", help="the lines to write")
    args = parser.parse_args()
    first, _, last = args.scans.partition(":")
    try:
        span = (int(first or 0), int(last) if last else None)
    except ValueError:
        parser.error(f"--scans {args.scans!r}: give A:B, two scan numbers (either may be left out), e.g. 0:200")
    for name, value, low in (("every", args.every, 1), ("beams", args.beams, 2)):
        if value is not None and value < low:
            parser.error(f"--{name} {value}: must be >= {low}")
    for name, value in (("noise", args.noise), ("clip", args.clip), ("no-return", args.no_return)):
        if value is not None and not (value >= 0 if name == "noise" else value > 0):
            parser.error(f"--{name} {value}: must be {'>= 0' if name == 'noise' else '> 0'} (m)")
    if not args.source.is_file():
        what = "is a folder" if args.source.is_dir() else "no such file"
        parser.error(f"{args.source}: {what}; give a CARMEN .log or .log.gz")
    if args.target.is_dir():
        parser.error(
            f"{args.target}: is a folder; give the derived log's file name, e.g. {args.target / 'derived.log.gz'}"
        )
    try:
        source = text_lines(args.source)
    except LogFormatError as exc:  # names the file itself
        parser.exit(2, f"error: {exc}\n")
    try:
        lines = derive(
            source,
            args.every,
            args.beams,
            args.clip,
            args.no_return,
            span,
            args.resample,
            args.noise,
            args.seed,
            args.message,
        )
        if not lines:
            raise LogFormatError(
                f"no FLASER scans to write (--scans {args.scans}, --every {args.every}); check the log"
            )
        data = ("\n".join(lines) + "\n").encode()
        atomic_write(args.target, lambda f: f.write(gzip.compress(data) if args.target.suffix == ".gz" else data))
    except OSError as exc:
        parser.exit(2, f"error: {exc.filename}: {exc.strerror}; check the path and its permissions\n")
    except LogFormatError as exc:
        parser.exit(2, f"error: {args.source}: {exc}\n")
    print(f"wrote {args.target}: {len(lines)} scans")


if __name__ == "__main__":
    main()
