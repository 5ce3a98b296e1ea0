"""Loss, risk, development paths and the evaluate-apps command (on a toy application and on the test room)."""

import json
import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import pytest
from typer.testing import CliRunner

from mi_lidar.apps.evaluate import evaluate_datasets, evaluate_log
from mi_lidar.apps.lines import LineDetection
from mi_lidar.apps.localization import ParticleFilter
from mi_lidar.apps.registration import ScanToMapEKF
from mi_lidar.apps.risk import (
    Objectives,
    Parameter,
    development_path,
    evaluate_application,
    sample_alphas,
)
from mi_lidar.cli import app as cli
from mi_lidar.core.errors import ParameterError
from mi_lidar.planar.protocol import PlanarProtocol
from tests.apps.room import room_ranges, room_states
from tests.core.test_strict_json import strict_load
from tests.planar.world import room_log_text
from tests.terminal import assert_whole, invoke_at_80

APPS = (ScanToMapEKF, ParticleFilter, LineDetection)


@dataclass
class Bowl:
    """A toy application: J = (a - 3 - offset)^2 + (b - 1)^2 where ``offset`` is the mean of the dataset's ranges."""

    sweep: ClassVar[str] = "a"
    name: str = "bowl"
    objective: str = "toy"
    parameters: tuple = (
        Parameter("a", (0.0, 1.0, 2.0, 3.0, 4.0, 5.0), start=0.0),
        Parameter("b", (0.0, 1.0, 2.0), start=2.0),
    )

    def evaluate(self, alpha, states, ranges):
        return {"J": (alpha["a"] - 3.0 - float(np.mean(ranges))) ** 2 + (alpha["b"] - 1.0) ** 2}


def test_development_path_descends_to_the_grid_minimum():
    app = Bowl()
    seen = []

    def objective(alpha):
        seen.append(alpha)
        return app.evaluate(alpha, None, np.zeros(1))["J"]

    path = development_path(app, objective, {"a": 0.0, "b": 2.0})
    assert path[0] == {"a": 0.0, "b": 2.0} and path[-1] == {"a": 3.0, "b": 1.0}
    values = [objective(a) for a in path]
    assert all(later < earlier for earlier, later in zip(values, values[1:]))


def test_prior_draws_come_from_the_grids_and_repeat_with_the_seed():
    app = Bowl()
    draws = sample_alphas(app, 50, seed=4)
    assert draws == sample_alphas(app, 50, seed=4)
    assert {d["a"] for d in draws} == set(app.parameters[0].values)
    with pytest.raises(ParameterError, match="start 7"):
        Parameter("c", (1.0, 2.0), start=7.0)


def test_risk_is_zero_for_a_perfect_simulator_and_grows_with_its_bias(tmp_path):
    ranges = {"real": np.zeros(4), "perfect": np.zeros(4), "biased": np.ones(4)}
    objectives = Objectives(None, ranges, tmp_path / "objectives.json", key="k")
    result = evaluate_application(Bowl(), objectives, m=12, seed=0)
    assert result.risk["perfect"] == 0.0 and result.risk["biased"] > 0.5
    assert result.picks["perfect"]["within"] and result.picks["perfect"]["real_J"] == 0.0
    # Developed on the biased simulator, the developer picks a = 4: real J = 1, not within 10 % of 0.
    assert result.picks["biased"]["alpha"]["a"] == 4.0 and not result.picks["biased"]["within"]
    # The sweep runs along a at the best real setting (a = 3, b = 1): real J = (a - 3)^2, biased J = (a - 4)^2.
    assert result.sweep["at"] == {"a": 3.0, "b": 1.0} and result.sweep["values"] == [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]
    assert [row["J"] for row in result.sweep["metrics"]["real"]] == [9.0, 4.0, 1.0, 0.0, 1.0, 4.0]
    assert [row["J"] for row in result.sweep["metrics"]["biased"]] == [16.0, 9.0, 4.0, 1.0, 0.0, 1.0]
    again = Objectives(None, ranges, tmp_path / "objectives.json", key="k")
    evaluate_application(Bowl(), again, m=12, seed=0)
    assert again.new == 0  # every value came from the file
    assert Objectives(None, ranges, tmp_path / "objectives.json", key="other").values == {}
    with pytest.raises(ParameterError, match="no 'real' source"):
        evaluate_application(Bowl(), Objectives(None, {"a": np.zeros(1)}), m=2)


def test_the_objectives_file_writes_an_undefined_metric_as_null_and_reads_it_back_as_nan(tmp_path):
    """Line detection's precision is NaN when it detects nothing: the cache file held NaN, which is not JSON."""

    class Undetected(Bowl):
        def evaluate(self, alpha, states, ranges):
            return {**super().evaluate(alpha, states, ranges), "precision": float("nan"), "J_runs": [1.0, math.nan]}

    objectives = Objectives(None, {"real": np.zeros(2)}, tmp_path / "objectives.json", key="k")
    first = objectives(Undetected(), "real", {"a": 1.0, "b": 1.0})
    objectives.save()
    stored = strict_load((tmp_path / "objectives.json").read_text())["values"]
    assert list(stored.values()) == [{"J": 4.0, "precision": None, "J_runs": [1.0, None]}]
    again = Objectives(None, {"real": np.zeros(2)}, tmp_path / "objectives.json", key="k")
    read = again(Undetected(), "real", {"a": 1.0, "b": 1.0})
    assert again.new == 0 and read["J"] == first["J"] == 4.0 and read["J_runs"][0] == 1.0
    assert math.isnan(read["precision"]) and math.isnan(read["J_runs"][1])


def test_evaluate_datasets_reports_every_application_and_resumes_from_its_cache(tmp_path, monkeypatch):
    states = room_states(scans=6, beams=91)
    ranges = {
        "real": room_ranges(states, sigma=0.03, short=0.15, seed=1),
        "clean": room_ranges(states, sigma=0.01, seed=2),
        "cluttered": room_ranges(states, sigma=0.03, short=0.15, seed=3),
    }
    first = evaluate_datasets(states, ranges, tmp_path, "room", key="room", draws=4, runs=1)
    report = json.loads((tmp_path / "apps.json").read_text())
    assert [a["application"] for a in report["applications"]] == ["registration", "localization", "lines"]
    for application in report["applications"]:
        assert set(application["risk"]) == {"clean", "cluttered"} and len(application["J"]["real"]) == 4
        assert application["paths"]["real"][0] == {p["name"]: p["start"] for p in application["parameters"]}
    lines = first.results[2]
    # Line detection on scans with the real share of clutter behaves as on the real scans; clean scans mislead.
    assert lines.risk["cluttered"] < lines.risk["clean"], lines.risk
    assert (tmp_path / "apps.html").stat().st_size > 5000 and len(list(tmp_path.glob("*.png"))) == 10
    for application in report["applications"]:  # standard errors of the risks and of their paired differences
        assert set(application["risk_se"]) == {"clean", "cluttered"} and application["risk_se"]["clean"] >= 0.0
        pair = application["paired_difference"]["clean"]["cluttered"]
        assert pair["mean"] == pytest.approx(application["risk"]["clean"] - application["risk"]["cluttered"])
    for c in APPS:
        monkeypatch.setattr(f"{c.__module__}.{c.__name__}.evaluate", _fail)
    # Side by side in forked processes, every value comes from the applications' caches.
    again = evaluate_datasets(states, ranges, tmp_path, "room", key="room", draws=4, runs=1, workers=3)
    assert [r.risk for r in again.results] == [r.risk for r in first.results]


@pytest.mark.slow
def test_evaluate_apps_on_the_room_log(tmp_path, monkeypatch):
    log = tmp_path / "room.log"
    log.write_text(room_log_text(scans=40))
    out = tmp_path / "report"
    args = ["evaluate-apps", str(log), "--out", str(out), "-s", "M0", "-s", "M1", "--draws", "3", "--runs", "1"]
    result = invoke_at_80([*args, "--window", "5"])
    assert result.exit_code == 0, result.stdout
    assert "registration" in result.stdout and "localization" in result.stdout and "lines" in result.stdout
    report = json.loads((out / "apps.json").read_text())
    assert_whole(result.stdout, *(f"{a['risk'][name]:.3g}" for a in report["applications"] for name in ("M0", "M1")))
    assert report["states"] == 40 and report["test_states"] == 8 and report["simulators"] == ["M0", "M1"]
    assert all(set(a["risk"]) == {"M0", "M1"} for a in report["applications"])
    # A rerun reads the simulated datasets from the cache.
    monkeypatch.setattr("mi_lidar.planar.benchmark.run_planar_benchmark", _fail)
    again = evaluate_log(log, out, protocol=PlanarProtocol(window=5.0), simulators=("M0", "M1"), draws=3, runs=1)
    assert [r.risk for r in again.results] == [r["risk"] for r in report["applications"]]


def _fail(*args, **kwargs):
    raise AssertionError("the cache was not used")


def test_unknown_simulator_is_named(tmp_path):
    log = tmp_path / "room.log"
    log.write_text(room_log_text(scans=10))
    result = CliRunner().invoke(cli, ["evaluate-apps", str(log), "--out", str(tmp_path), "-s", "M9"])
    assert result.exit_code == 2 and "unknown simulators ['M9']" in result.stdout
