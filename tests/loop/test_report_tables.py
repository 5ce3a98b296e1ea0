"""The compare report's Markdown tables keep their columns when a header or cell contains `|`."""

from mi_lidar.io.markdown import markdown_to_html
from mi_lidar.loop.report import markdown_table


def test_pipes_in_headers_and_cells_are_escaped():
    rows = [{"group": "label a|b", "range_error_mean": 0.25}, {"group": "x", "range_error_mean": 1.5}]
    md = markdown_table(rows, ["group", "range_error_mean"])
    lines = md.splitlines()
    assert lines[0] == r"| group | mean \|range error\| (m) |"
    # Every row has as many unescaped separators as the header: 3 for 2 columns.
    assert all(line.replace(r"\|", "").count("|") == 3 for line in lines)
    page = markdown_to_html(md, "t")
    assert "<th>mean |range error| (m)</th>" in page and "<td>label a|b</td>" in page
    assert page.count("<td>") == 4


def test_an_image_whose_alt_text_names_an_effect_with_options_keeps_its_link():
    """diagnosis.html showed `<img src="law=cos)](before_after_1.png">`: the link was read from the first '('."""
    md = "![before and after incidence_dropout(law=cos), range_bias(bias=[0.1])](before_after_1.png)"
    page = markdown_to_html(md, "t")
    assert (
        '<img src="before_after_1.png" alt="before and after incidence_dropout(law=cos), range_bias(bias=[0.1])"'
        in page
    )
