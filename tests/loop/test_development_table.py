"""The development path's tables read whole in an 80-column terminal, and a step that was not kept says so."""

from rich.console import Console

from mi_lidar.loop.development import Step, development_table
from tests.terminal import WIDTH, assert_whole

SAMPLES = {"range_error_median": 0.0615, "histogram_l1": 0.0123, "f1": 0.991}
NOISE = {"range_noise.sigma0": 0.0123456, "range_noise.k": 0.00234567}


def test_the_development_path_prints_whole_at_80_columns():
    rows = [
        Step("bare mesh", "-", 11.873, 11.901, {}, SAMPLES),
        Step("mesh + effects", "+ range_noise(law=footprint)", 7.361, 7.402, NOISE, SAMPLES),
        Step(
            "mesh + effects", "+ corner_returns", 7.301, 7.35, {**NOISE, "corner_returns.share": 0.25}, SAMPLES, "worse"
        ),
    ]
    console = Console(width=WIDTH, record=True)
    console.print(development_table(rows, "Ouster OS-1-32 frame"))
    text = console.export_text()
    assert_whole(text, "11.873", "7.402", "7.350", "0.061", "0.012", "0.991", "corner_returns.share=0.25")
    assert "(not kept:" in text  # a step the realism guard refused is marked (a [...] note was eaten as markup)
