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


def test_fitted_values_read_as_a_number_a_short_list_or_their_spread():
    """diagnose's verdict wrote ``sigma0=[0.0822]`` and a per-beam bias as numpy's ``[0.0359 0.0359 ... 0.0359]``."""
    import numpy as np

    from mi_lidar.loop.diagnosis_report import values_text

    assert values_text(np.array([0.08219], np.float32)) == "0.08219"
    assert values_text([0.5, 2.0]) == "[0.5, 2]"
    assert values_text(np.full(180, 0.03, np.float32)) == "[180 values: min 0.03, median 0.03, max 0.03, RMS 0.03]"


def test_the_compare_report_names_a_per_beam_effect_by_its_spread(tmp_path):
    """compare's report began 'Model: range sigma 0.01 m, effects: range_bias(bias=[0.02 0.02 ...' with a value per
    beam (360 on the room's scanner)."""
    import dataclasses

    import numpy as np

    from mi_lidar.core.effects import parse_effects
    from mi_lidar.loop import compare
    from mi_lidar.scene.simulation import simulate

    from .helpers import room

    scene, model, poses = room(1)
    log = simulate(scene, poses=poses, model=model, seed=1)
    bias = "range_bias(bias=[" + ", ".join(f"{b:.3f}" for b in np.linspace(0.0, 0.02, 360)) + "])"
    biased = dataclasses.replace(model, effects=parse_effects(bias))
    compare(log, scene, biased, out=tmp_path)
    head = (tmp_path / "report.md").read_text().splitlines()[2]
    assert head.startswith("Model: range sigma 0.01 m, effects: range_bias (bias: [360 values: min 0, median 0.01")
    assert len(head) < 200


def test_the_note_on_rays_that_meet_nothing_appears_only_with_such_rays(tmp_path):
    """Every compare report ended with "Group `none`: rays that meet no element ..." under tables without such a
    group (the README's room, the Intel wall map): a note on nothing."""
    import dataclasses

    from mi_lidar.loop import compare
    from mi_lidar.scene.simulation import simulate

    from .helpers import room

    scene, model, poses = room(1)
    log = simulate(scene, poses=poses, model=model, seed=1)
    note = "Group `none`: rays that meet no element"
    compare(log, scene, model, out=tmp_path / "closed")
    closed = (tmp_path / "closed" / "report.md").read_text()
    assert "| none |" not in closed and note not in closed
    compare(log, scene, dataclasses.replace(model, max_range=2.0), out=tmp_path / "short")  # far walls out of range
    short = (tmp_path / "short" / "report.md").read_text()
    assert "| none |" in short and note in short
