"""Intensity calibrated on real frames: Ouster OS-1-32 REFLECTIVITY and SIGNAL, VLP-16 reflectivity.

Results and protocol: docs/loop_results.md.

Run:  python examples/05_real_intensity.py [OUT]
For each channel it builds the range-image mesh of columns 0 mod 4, starts every face from its
vertices' intensities, calibrates the intensity curve, noise and per-face reflectivities on columns
2 mod 4 (the reflectivities shrunk toward their start by a width chosen on columns 1 mod 4), and
scores columns 3 mod 4 against a constant per beam. OUT/report.html holds the table and the figure.
OUT defaults to reports/intensity_real/. About 1 minute on 2 cores.
"""

import argparse
from pathlib import Path

import numpy as np
from rich.console import Console

from mi_lidar.io import read_any
from mi_lidar.loop.real_intensity import intensity_experiment, write_intensity_report

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"

if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", nargs="?", default="reports/intensity_real", help="report folder (default: %(default)s)")
    out = Path(parser.parse_args().out)
    console = Console()
    ouster = read_any(DATA / "ouster" / "OS-1-32-G_v2.1.1_1024x10.pcap")
    velodyne = read_any(DATA / "velodyne" / "velodyne_vlp16.pcap")
    # the capture's longest scan: 1,464 columns, about 0.81 of a revolution (no scan of it is whole)
    longest = velodyne.scan(int(np.argmax(velodyne.hit.sum(axis=(1, 2)))))
    scores = []
    for log, attribute, law in (
        (ouster, "reflectivity", "reflectivity"),
        (ouster, "signal", "signal"),
        (longest, "intensity", "reflectivity"),
    ):
        with console.status(f"calibrating {log.sensor['name']} {attribute}"):
            scores.append(intensity_experiment(log, attribute, law))
        console.print(scores[-1].summary())
    console.print(f"report: {write_intensity_report(scores, out)}")
