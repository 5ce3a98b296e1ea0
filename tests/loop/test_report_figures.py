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


def test_the_structure_figure_draws_many_beams_as_a_band_and_one_label_as_a_note(monkeypatch, tmp_path):
    """On Intel (180 beams, one label) the beam panels were 180 overlapping error bars, a solid smear, and the
    label panels one point over an axis from 0.96 to 1.04."""
    saved = capture(monkeypatch, report)
    found = [structure(d, c, n) for d, n in (("beam", 180), ("range", 12), ("label", 1)) for c in ("range", "returns")]
    residuals.plot_structure(found, tmp_path / "s.png")
    axes = [a for a in saved["figure"].axes if a.get_visible()]
    beam, few, label = axes[:3]
    assert not beam.containers and len(beam.collections) == 1  # one band, no error bars
    assert len(few.containers) == 1  # 12 groups: error bars
    assert "nothing to compare" in label.texts[0].get_text() and not label.lines and not len(label.get_yticks())


def test_the_verdict_of_the_structure_left_names_the_guide_once_with_a_paragraph_per_dimension():
    """Six flagged dimensions made one paragraph of 20 terminal lines, each sentence ending with the guide."""
    flagged = [
        Structure(d, c, np.arange(3.0), np.zeros(3), np.ones(3), 50.0, 2, 1e-9, 0.02, True)
        for d, c in (("time", "returns"), ("range", "returns"), ("beam", "range"))
    ]
    text = residuals.structure_verdict(flagged)
    paragraphs = text.split("\n\n")
    assert len(paragraphs) == 4 and all("varies with" in p for p in paragraphs[:3])
    assert text.count(residuals.GUIDE) == 1 and paragraphs[-1].startswith("To model what no catalog effect explains")
    assert residuals.structure_verdict(flagged[:1]).endswith(f"To model it, write a new effect ({residuals.GUIDE}).")


def test_the_breakdown_figure_draws_every_beam(monkeypatch, tmp_path):
    """The panel by beam drew every 9th of Freiburg 079's 360 beams (40 bars) and said nothing of it."""
    saved = capture(monkeypatch, report)

    def rows(n: int, name: str) -> list[dict]:
        return [
            {"group": f"{name} {i}", "nll": 1.0 + i % 7, "hit_rate_measured": 0.9, "hit_rate_simulated": 1.0}
            for i in range(n)
        ]

    groups = {"range": 6, "incidence": 6, "azimuth": 6, "beam": 360, "label": 1, "time": 10}
    result = SimpleNamespace(breakdowns={k: rows(n, k) for k, n in groups.items()}, headline={"nll": 3.0})
    report.plot_breakdowns(result, tmp_path / "b.png")
    panels = {a.get_title(): a for a in saved["figure"].axes if a.get_title()}
    assert len(panels["by beam"].patches) == 360 and len(panels["by time"].patches) == 10
    assert len(panels["by beam"].get_xticklabels()) == report.MAX_GROUP_LABELS  # names still thinned


def test_the_group_of_rays_that_met_nothing_is_drawn_apart(monkeypatch, tmp_path):
    """compare on Intel in a crude box scene: 87 of 163,800 rays met no element (group 'none'); the sensor returned
    98.9 % of them and the model none, and the simulated hit-rate line ran from 1.0 at '20-40 m' down to 0 at 'none'
    as if the rate fell with range. 'none' is not a step of the range, incidence or label axis: its rates are drawn
    as marks apart (after a divider, its ray count under it), not joined to the other groups' lines."""
    saved = capture(monkeypatch, report)

    def rows(names: list[str]) -> list[dict]:
        line = [
            {"group": g, "rays": 1000, "nll": 9.0, "hit_rate_measured": 0.97, "hit_rate_simulated": 1.0} for g in names
        ]
        nothing = {"group": "none", "rays": 87, "nll": 20.5, "hit_rate_measured": 0.989, "hit_rate_simulated": 0.0}
        return line + [nothing]

    ordered = {"range": ["0-1 m", "1-2 m", "20-40 m"], "incidence": ["00-15 deg", "75-90 deg"], "label": ["label 1"]}
    groups = {**ordered, "azimuth": ["-090..-060 deg"], "beam": ["beam 000"], "time": ["scans 0-9"]}
    result = SimpleNamespace(breakdowns={k: rows(v) for k, v in groups.items()}, headline={"nll": 9.3})
    report.plot_breakdowns(result, tmp_path / "b.png")
    figure = saved["figure"]
    panels = {a.get_title(): a for a in figure.axes if a.get_title()}
    for name, names in ordered.items():
        ax = panels[f"by {name}"]
        [twin] = [a for a in figure.axes if a is not ax and a.bbox.bounds == ax.bbox.bounds]
        apart = len(names)  # the x of group 'none'
        joined = [line for line in twin.lines if line.get_linestyle() not in ("None", "")]
        marks = [line for line in twin.lines if line.get_linestyle() in ("None", "")]
        assert all(apart not in np.asarray(line.get_xdata()) for line in joined), name
        drawn = sorted(float(y) for line in marks for x, y in zip(line.get_xdata(), line.get_ydata()) if x == apart)
        assert drawn == [0.0, 0.989], name
        assert [t.get_text() for t in ax.get_xticklabels()][-1] == "none (87 rays)"
