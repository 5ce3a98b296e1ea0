"""The loop on a log with a hidden effect: compare, diagnose, add the effect, compare again.

Run:  python examples/01_loop_hidden_effect.py [OUT_DIR]
It simulates 24 scans of scenes_xml/indoor_planar.xml with incidence-angle dropout hidden in the
log, finds that effect among candidates, and writes before/after reports to OUT_DIR (default
out/loop_demo). See docs/tutorial_loop.md.
"""

import argparse

import mi_lidar  # noqa: F401  (selects the variant, registers the plugins)
from mi_lidar.loop.demo import run_demo

if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "out", nargs="?", default="out/loop_demo", help="folder of the before/after reports (default: %(default)s)"
    )
    result = run_demo(out=parser.parse_args().out)
    print("selected:", result["selected"])
