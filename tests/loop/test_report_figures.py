"""The loop's figures on a planar log (N beams x 1 firing): no empty panels, no images one pixel wide."""

from types import SimpleNamespace

import numpy as np

from mi_lidar.loop import report, residuals
from mi_lidar.loop.residuals import Structure


def capture(monkeypatch, module) -> dict:
    saved = {}
    monkeypatch.setattr(module, "save_figure", lambda figure, path: saved.setdefault("figure", figure) and path)
    return saved


def structure(dimension: str, channel: str, groups: int) -> Structure:
    centers = np.arange(float(groups))
    return Structure(
        dimension, channel, centers, np.zeros(groups), np.ones(groups), 1.0, max(groups - 1, 0), 0.5, 0.0, False
    )


def test_the_structure_figure_has_a_column_per_dimension_with_groups_only(monkeypatch, tmp_path):
    """A planar log has one beam: its beam panels were left as two empty columns."""
    saved = capture(monkeypatch, report)
    found = [structure(d, c, 5) for d in ("time", "range", "label") for c in ("range", "returns")]
    found.append(structure("beam", "range", 0))
    residuals.plot_structure(found, tmp_path / "s.png")
    axes = saved["figure"].axes
    assert len(axes) == 6 and all(a.get_visible() for a in axes)
    assert [a.get_xlabel().split(" ")[0] for a in axes[:3]] == ["time", "range", "label"]


def test_a_planar_scan_is_drawn_as_curves_over_the_beams(monkeypatch, tmp_path):
    saved = capture(monkeypatch, report)
    beams = 360
    rng = np.random.default_rng(0)
    nominal = 2.0 + rng.random(beams)
    hit = rng.random(beams) > 0.1
    t = SimpleNamespace(
        scan=np.zeros(beams, int),
        beam=np.arange(beams),
        column=np.zeros(beams, int),
        ll=-rng.random(beams),
        hit=hit,
        measured=nominal + 0.01 * rng.standard_normal(beams),
        nominal=nominal,
        sim_hit=rng.random(beams) > 0.1,
        sim_range=nominal + 0.01 * rng.standard_normal(beams),
    )
    report.plot_residual_image(t, (1, beams, 1), tmp_path / "r.png")
    axes = saved["figure"].axes
    assert len(axes) == 3 and axes[-1].get_xlabel() == "beam"
    drawn = axes[0].lines[0].get_xdata()
    assert len(drawn) == beams and drawn.max() == beams - 1  # one point per beam, not a one-pixel column
    figure = saved["figure"]
    figure.canvas.draw()
    box = axes[0].get_legend().get_window_extent()
    for line in axes[0].lines:  # the legend sat on the farthest ranges, top right
        xy = axes[0].transData.transform(np.c_[line.get_xdata(), line.get_ydata()])
        inside = (box.x0 <= xy[:, 0]) & (xy[:, 0] <= box.x1) & (box.y0 <= xy[:, 1]) & (xy[:, 1] <= box.y1)
        assert not inside.any(), line.get_label()


def test_a_breakdown_of_many_groups_names_at_most_twenty():
    """40 beams on a 5-inch panel: every label was drawn and they overlapped; now every second one."""
    import matplotlib.pyplot as plt

    figure, ax = plt.subplots()
    names = [f"beam {i:03d}" for i in range(40)]
    report.label_groups(ax, names)
    shown = [t.get_text() for t in ax.get_xticklabels()]
    assert len(shown) == 20 and shown[:2] == ["beam 000", "beam 002"] and list(ax.get_xticks()[:2]) == [0, 2]
    report.label_groups(ax, names[:7])
    assert [t.get_text() for t in ax.get_xticklabels()] == names[:7]
    plt.close(figure)
