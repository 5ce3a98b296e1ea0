"""The demo's ranking fits 80 columns (a 31-character candidate pushed 'significant' onto its own line), so does
the rule above the loop, and the demo ends by naming the reports it wrote."""

import io
from types import SimpleNamespace

from rich.console import Console

from mi_lidar.cli.render import LOOP_TITLE
from mi_lidar.loop.demo import ranking_lines, run_demo

from ..terminal import WIDTH, assert_whole


def test_the_ranking_keeps_one_line_per_candidate_in_80_columns():
    names = ["incidence_dropout(law=cos)", "incidence_dropout(law=logistic)", "outliers"]
    rows = [
        SimpleNamespace(name=n, test_gain=4.9975, k=2, delta_bic=-40141.4, significant=i < 2)
        for i, n in enumerate(names)
    ]
    lines = ranking_lines(rows)
    assert len(lines) == 4 and all(len(line) <= 80 for line in lines), [len(line) for line in lines]
    assert lines[2].endswith("significant") and lines[3].endswith("-")
    assert len({line.index("+4.9975") for line in lines[1:]}) == 1  # the figures in one column


def test_the_rule_above_the_demos_loop_is_whole_in_80_columns():
    """`make demo` printed '─ The loop: a log with a hidden effect, its diagnosis, the error before and a… ─'."""
    console = Console(width=WIDTH, file=io.StringIO(), record=True)
    console.rule(LOOP_TITLE)
    assert_whole(console.export_text(), LOOP_TITLE)


def test_the_demo_ends_naming_the_reports_it_wrote(tmp_path, capsys):
    """`make demo` ended on its F1 note: nothing said that demo_out/loop held a diagnosis and two HTML reports.
    Printed as plain text (examples/01), the verdict showed its Markdown: 'missing **incidence_dropout(law=cos)**'."""
    run_demo(out=tmp_path / "loop", candidates=["incidence_dropout"])
    lines = capsys.readouterr().out.splitlines()
    assert any("missing incidence_dropout(law=cos) (gamma=" in line for line in lines), lines
    assert not any("**" in line for line in lines), lines
    reports = [tmp_path / "loop" / name for name in ("diagnosis.html", "before/report.html", "after/report.html")]
    assert lines[-1] == "reports: " + ", ".join(map(str, reports)), lines[-1]
    assert all(report.is_file() for report in reports)
