"""The loss figure's legend quotes the risk's standard error the report's table quotes; the 3D report's figures
say what they show."""

from types import SimpleNamespace

import numpy as np

from mi_lidar.apps import report, report3d
from mi_lidar.apps.risk import AppResult


def result() -> AppResult:
    J = {
        "real": np.array([1.0, 2.0, 3.0]),
        "gaussian": np.array([1.5, 2.5, 2.0]),
        "mi-lidar": np.array([1.1, 2.2, 2.9]),
    }
    risk = {name: float(np.mean(np.abs(J[name] - J["real"]))) for name in ("gaussian", "mi-lidar")}
    return AppResult(
        name="matching",
        objective="error (m)",
        parameters=[],
        alphas=[{}, {}, {}],
        J=J,
        risk=risk,
        paths={},
        path_J={},
        best_real=(1.0, {}),
        picks={},
        risk_se={"gaussian": 0.111, "mi-lidar": 0.0222},  # over the draws
    )


def legend_of(monkeypatch, tmp_path, **options) -> list[str]:
    saved = {}
    monkeypatch.setattr(report, "_save", lambda figure, path: saved.setdefault("figure", figure) and path)
    report.loss_figure(result(), tmp_path / "loss.png", **options)
    return [text.get_text() for text in saved["figure"].axes[0].get_legend().get_texts()]


def test_the_legend_quotes_the_draws_standard_error_by_default(monkeypatch, tmp_path):
    assert legend_of(monkeypatch, tmp_path) == ["gaussian (risk 0.667 ± 0.11)", "mi-lidar (risk 0.133 ± 0.022)"]


def test_the_legend_quotes_the_standard_error_it_is_given(monkeypatch, tmp_path):
    """The 3D report's table gives a bootstrap over the starts: its figure must quote the same."""
    labels = legend_of(monkeypatch, tmp_path, risk_se={"gaussian": 0.02, "mi-lidar": 0.014})
    assert labels == ["gaussian (risk 0.667 ± 0.02)", "mi-lidar (risk 0.133 ± 0.014)"]


def test_a_path_of_one_step_has_integer_ticks_and_a_whole_y_label(monkeypatch, tmp_path):
    """Developed on a simulator whose first step was its last: one point (its ticks were -0.04 ... 0.04)."""
    r = result()
    r.objective = "pose error over the starts: translation (m) + 10 m x rotation (rad), mean over the frames"
    r.paths = {"real": [{}], "mi-lidar": [{}, {}, {}]}
    r.path_J = {"real": ([0.01], [0.01]), "mi-lidar": ([0.03, 0.02, 0.015], [0.01, 0.012, 0.011])}
    saved = {}
    monkeypatch.setattr(report, "_save", lambda figure, path: saved.setdefault("figure", figure) and path)
    report.path_figure(r, tmp_path / "paths.png")
    figure = saved["figure"]
    figure.canvas.draw()
    single = figure.axes[0]
    ticks = [t for t in single.get_xticks() if single.get_xlim()[0] <= t <= single.get_xlim()[1]]
    assert ticks == [0.0, 1.0], ticks
    label = single.yaxis.label.get_window_extent()
    assert label.height <= figure.bbox.height, "the y label runs off the figure"


def test_the_scans_figure_has_a_title_and_axes_in_metres(monkeypatch, tmp_path):
    """``scans.png`` of ``evaluate-apps-3d`` showed seven panels of points with no title and no axis labels."""
    directions = np.c_[np.cos(np.linspace(0, 6, 50)), np.sin(np.linspace(0, 6, 50)), np.zeros(50)]
    states = SimpleNamespace(origins=np.zeros((50, 3)), directions=directions)
    evaluation = SimpleNamespace(simulators=["gaussian", "mi-lidar"], states=states)
    saved = {}
    monkeypatch.setattr(report3d, "_save", lambda figure, path: saved.setdefault("figure", figure) and path)
    report3d.scans_figure(
        evaluation, dict.fromkeys(["real", "gaussian", "mi-lidar"], np.full(50, 5.0)), tmp_path / "s.png"
    )
    figure = saved["figure"]
    assert "from above" in figure.get_suptitle() and "30 m" in figure.get_suptitle()
    assert figure.get_supxlabel() == "x from the sensor (m)" and figure.get_supylabel() == "y from the sensor (m)"
    assert [axis.get_title() for axis in figure.axes[:3]] == [
        "real: 50 points",
        "gaussian: 50 points",
        "mi-lidar: 50 points",
    ]


def test_the_reports_print_parameter_grids_as_numbers_not_floats():
    """apps3d.html read 'iterations in [5.0, 10.0, 20.0, 40.0]' (the grids are stored as floats)."""
    grids = [
        {"name": "iterations", "values": [5.0, 10.0, 20.0, 40.0], "unit": ""},
        {"name": "voxel", "values": [0.1, 0.2], "unit": "m"},
    ]
    assert report.grids_text(grids) == "iterations in [5, 10, 20, 40], voxel in [0.1, 0.2] m"
