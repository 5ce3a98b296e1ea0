"""The demo's ranking fits 80 columns (a 31-character candidate pushed 'significant' onto its own line)."""

from types import SimpleNamespace

from mi_lidar.loop.demo import ranking_lines


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
