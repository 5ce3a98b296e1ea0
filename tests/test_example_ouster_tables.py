"""examples/04_real_ouster.py prints its development path in tables that read whole in an 80-column terminal."""

import importlib.util
import re

from rich.console import Console

from mi_lidar.loop.development import Step
from tests.conftest import REPO
from tests.terminal import WIDTH, assert_whole

SAMPLES = {"range_error_median": 0.0762, "histogram_l1": 1.248, "f1": 0.923}
WORSE = "samples worse: histogram_l1 1.23 -> 1.46, chamfer 0.345 -> 0.481, stray 0.422 -> 0.649"
ROWS = [  # the path the example printed on the shared Ouster frame
    Step("range-image mesh, opaque, sigma 1 cm", "(mesh only)", 13.459, 13.882, {"test returns at the floor": 9121}),
    Step("range-image mesh", "+ corner_returns", 9.974, 11.191, {"corner_returns.share": 0.6213}, SAMPLES),
    Step("range-image mesh", "+ range_noise (footprint)", 7.223, 7.612, {"range_noise.k": 0.01044}, SAMPLES, WORSE),
    Step("range-image mesh", "+ label_dropout (faces closing holes)", 7.360, 8.493, {"label_dropout.drop": 0.05017}),
]


def path_tables():
    spec = importlib.util.spec_from_file_location("real_ouster_example", REPO / "examples" / "04_real_ouster.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.path_tables


def test_the_development_path_reads_whole_at_80_columns():
    console = Console(width=WIDTH, record=True)
    console.print(path_tables()(ROWS, "Ouster OS-1-32 frame: test rays (odd columns), 1 cm bins"))
    text = console.export_text()
    labels = ("│ mesh only ", "│ + corner_returns ", "│ + range_noise (not kept) ", "│ + label_dropout ")
    assert_whole(text, *labels, "13.459", "8.493", "0.076", "1.248", "0.923", "corner_returns.share", "0.6213")
    flat = re.sub(r"\s+", " ", text)  # the caption and the notes wrap between words, never inside one
    added = "Added as: range_noise (footprint), label_dropout (faces closing holes)."
    assert added in flat and f"range_noise not kept: {WORSE}" in flat, text
