"""The calibrate command end to end, and its bad-input errors."""

import json
import re

import mitsuba as mi
import numpy as np
import pytest
from rich.console import Console
from typer.testing import CliRunner

import mi_lidar
from mi_lidar.calibration.commands import calibrate_command
from mi_lidar.calibration.fit import Calibration, FitOptions
from mi_lidar.cli import app
from mi_lidar.core.elements import ElementTable
from mi_lidar.core.errors import CalibrationError, SensorMismatchError
from mi_lidar.core.problem import Problem
from mi_lidar.core.rays import LogRays
from mi_lidar.scene.dicts import save_scene, scene_dict
from tests.terminal import assert_whole, invoke_at_80

from .scenes import SENSOR_HEIGHT, bowl, bowl_height, pattern, sensor_pose, shrubs

P_SHRUBS = [0.3, 0.6, 0.45, 0.7]
BIAS = 0.02  # m, on every beam


def sensor_xml(effects: str = "") -> str:
    z = bowl_height(0.0, 0.0) + SENSOR_HEIGHT
    effects_xml = f'<string name="effects" value="{effects}"/>' if effects else ""
    return (
        f'    <sensor type="lidar" id="lidar"><string name="pattern" value="vlp16"/>'
        f'<integer name="firings" value="400"/><float name="range_sigma" value="0.02"/>'
        f'<transform name="to_world"><translate z="{z}"/></transform></sensor>\n'
        f'    <integrator type="lidar_integrator">{effects_xml}</integrator>'
    )


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("calibrate")
    truth = save_scene(
        tmp / "truth.xml",
        {"terrain": bowl(n=9), "shrubs": shrubs(P_SHRUBS)},
        extra_xml=sensor_xml(f"range_bias(bias={BIAS})"),
    )
    start = save_scene(tmp / "start.xml", {"terrain": bowl(n=9), "shrubs": shrubs([0.5] * 4)}, extra_xml=sensor_xml())
    pose = mi_lidar.scene.scene_lidar_sensor(mi_lidar.load_scene(truth)).to_world_matrix
    poses = np.stack([pose] * 6)
    poses[:, 0, 3] = np.linspace(-0.5, 0.5, 6)
    log = mi_lidar.simulate(mi_lidar.load_scene(truth), poses=poses, seed=2)
    return tmp, log.save(tmp / "log.npz"), start


def test_calibrate_recovers_truth_and_writes_report(files):
    tmp, log, start = files
    out = tmp / "out"
    result, written = calibrate_command(
        log, start, ["elements.shrubs.p_hit", "sensor.range_bias"], out, steps=80, batch_size=1 << 14, eval_every=5
    )
    assert np.abs(result.fitted["sensor.range_bias"] - BIAS).max() < 0.005
    assert np.abs(result.fitted["elements.shrubs.p_hit"] - P_SHRUBS).max() < 0.05
    held = [h for _, _, h in result.history if np.isfinite(h)]
    assert held[-1] < held[0] and result.fitted_nll < result.initial_nll
    report = json.loads((out / "report.json").read_text())
    assert report["held_out_nll"]["fitted"] == pytest.approx(result.fitted_nll)
    assert {p.name for p in written.values()} >= {"scene.xml", "loss.png", "changes.csv", "history.csv", "report.html"}
    page = (out / "report.html").read_text()  # one page: NLL before and after, the parameter table, the loss trace
    assert f"{result.fitted_nll:.4f}" in page and "sensor.range_bias" in page and 'src="loss.png"' in page
    # Samples beside the likelihood: the fitted model's scan matches the measured one better (the
    # start's range bias is gone) and the page shows both rows.
    samples = report["held_out_samples"]
    assert samples["fitted"]["nll"] == pytest.approx(result.fitted_nll, abs=1e-3)
    assert samples["fitted"]["histogram_l1"] < samples["initial"]["histogram_l1"]
    assert samples["fitted"]["chamfer"] < samples["initial"]["chamfer"]
    assert "Samples beside the likelihood" in page and "Chamfer" in page
    # The table's headers are words, and the 16 per-beam biases read as their spread, not 16 floats (the page
    # showed 'mean_before' and 'range_bias(bias=[0.0201 0.0199 ...])' with every beam's value); the JSON keeps them.
    assert "<th>mean before</th>" in page and "<th>max |change|</th>" in page and "mean_before" not in page
    assert "Fitted sensor.range_bias (m): 16 values: min " in page and "RMS " in page
    assert "range_bias (bias: [16 values: min " in page and not re.search(r"(\d\.\d+[ ,]+){8}", page)
    assert len(report["effects"][0].split()) == 16  # 'range_bias(bias=[v0 v1 ... v15])'
    # The calibrated scene reloads with the fitted values, sensor and effect.
    scene = mi_lidar.load_scene(out / "scene.xml")
    table = ElementTable.from_scene(scene)
    k = table.shape_ids.index("shrubs")
    first = sum(table.element_counts[:k])
    np.testing.assert_allclose(
        np.asarray(table.p_hit)[first : first + 4], result.fitted["elements.shrubs.p_hit"], atol=1e-6
    )
    params = mi.traverse(scene.integrator())
    np.testing.assert_allclose(
        np.asarray(params["effects.range_bias.bias"]), result.fitted["sensor.range_bias"], atol=1e-6
    )


def test_cli_prints_table(files):
    """The tables fit an 80-column terminal: a long parameter name and the held-out NLL are printed whole."""
    tmp, log, start = files
    run = invoke_at_80(
        [
            "calibrate",
            log,
            start,
            "--params",
            "sensor.range_bias",
            "--params",
            "elements.*.range_sigma",
            "--out",
            tmp / "cli",
            "--steps",
            "5",
            "--batch-size",
            "4096",
        ],
    )
    assert run.exit_code == 0, run.output
    assert "held-out NLL" in run.output and (tmp / "cli" / "scene.xml").is_file()
    # The held-out NLL is evaluated every few steps: the progress lines and history.csv leave the
    # other steps out (they printed and wrote 'nan').
    assert "nan" not in run.output.lower() and "calibrating: loss" in run.output
    history = (tmp / "cli" / "history.csv").read_text().splitlines()
    report = json.loads((tmp / "cli" / "report.json").read_text())
    # the per-beam bias starts shared: 5 steps of the shared start, then 5 per beam, one history row each
    assert report["steps_run"] == 10 and set(report["shared_start"]) == {"sensor.range_bias"}
    assert history[0] == "step,train_nll,held_out_nll" and len(history) == 12
    assert [int(row.split(",")[0]) for row in history[1:]] == list(range(11))
    assert "nan" not in "".join(history).lower() and history[2].endswith(",")
    assert "shared start" in run.output
    fitted = report["held_out_nll"]["fitted"]
    assert_whole(run.stdout, "elements.terrain.range_sigma", f"{fitted:.4f}")  # as report.html writes it
    # the 16 per-beam biases as their spread (the table showed only their mean, to 6 digits)
    assert_whole(run.stdout, "fitted values", "RMS")
    spreads = run.stdout.split("fitted values")[1].split("held-out NLL")[0]
    assert "sensor.range_bias" in spreads and "elements.terrain.range_sigma" in spreads
    assert not re.search(r"\d\.0*[1-9]\d{5,}", run.stdout.split("calibrating: done")[-1])  # 6 significant digits
    bad = CliRunner().invoke(
        app, ["calibrate", str(log), str(start), "--params", "elements.*.nothing", "--out", str(tmp / "bad")]
    )
    assert bad.exit_code == 2 and "matches no parameter" in bad.output


def test_the_progress_bar_keeps_its_total_through_the_shared_start(files, monkeypatch):
    """On a terminal the bar showed 0/20 to 16/20 while the shared start ran, then 21/40 once the per-beam fit began
    (the shared start's steps plus 20): its total changed in the middle of the run. It now counts every step of both
    fits against the most they can take (2 x 20), known when the fit starts; an early stop ends it full at the count
    it reached, as every bar does."""
    import io

    from mi_lidar.cli import progress as progress_module

    tmp, log, start = files
    out = io.StringIO()
    monkeypatch.setattr(progress_module, "console", Console(file=out, force_terminal=True, width=120))
    args = ["calibrate", log, start, "-p", "sensor.range_bias", "--out", tmp / "bar", "--steps", "20"]
    run = invoke_at_80([*args, "--batch-size", "4096"])
    assert run.exit_code == 0, run.output
    counts = [
        tuple(map(int, m)) for m in re.findall(r"(\d+)/(\d+)", re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", out.getvalue()))
    ]
    report = json.loads((tmp / "bar" / "report.json").read_text())
    reached = report["steps_run"]
    assert set(report["shared_start"]) == {"sensor.range_bias"} and counts, out.getvalue()
    assert {total for _, total in counts} <= {40, reached}, counts  # 40 from the first step on; the end: reached
    assert counts[-1] == (reached, reached)


def test_glob_matching_nothing_lists_names(files):
    _, log, start = files
    with pytest.raises(CalibrationError, match="matches no parameter; available: .*elements.terrain.p_hit"):
        Calibration(mi_lidar.load_scene(start), mi_lidar.Log.load(log), ["sensor.focal_length"])


def test_log_from_another_sensor_is_rejected(files):
    tmp, log, start = files
    text = start.read_text().replace('value="vlp16"', 'value="hdl32e"')
    other = tmp / "other.xml"
    other.write_text(text)
    with pytest.raises(SensorMismatchError, match=r"does not match the scene's `lidar` sensor.*16 beams vs 32"):
        Calibration(mi_lidar.load_scene(other), mi_lidar.Log.load(log), ["elements.*.p_hit"])


def test_returns_no_element_explains_cost_the_floor_and_still_fit():
    # The log's shrubs stand 5 m from the sensor and the model's 7 m: no element can produce the
    # returns, so each costs the one floor of the score (log 1e-9 = -20.7 nats) instead of making
    # the loss infinite, and the fit runs to a finite held-out NLL.
    log = mi_lidar.simulate(
        mi_lidar.load_scene(scene_dict({"shrubs": shrubs(P_SHRUBS)})), pattern(100), poses=sensor_pose(), seed=1
    )
    model_scene = mi_lidar.load_scene(scene_dict({"shrubs": shrubs(P_SHRUBS, radius=7.0)}))
    robust = Calibration(model_scene, log, ["sensor.range_bias"], options=FitOptions(steps=2, counting_start=False))
    assert np.isfinite(robust.fit().fitted_nll)
    scored = Problem.build(model_scene, LogRays.from_log(log)).log_likelihood(robust.model)
    floor = np.log(1e-9)
    assert scored.min() >= floor - 1e-3  # nothing costs more than the floor
    assert np.sum(scored < floor + 0.1) > 100  # the unexplained returns cost about the floor


def test_a_shared_start_that_the_fit_beam_by_beam_did_not_beat_is_said_to_be_kept():
    """Intel (--pattern log, -p sensor.range_bias): 180 equal per-beam biases, shared start and fitted NLL both 3.7888,
    and nothing said why."""
    from types import SimpleNamespace

    from mi_lidar.calibration.report import SHARED_KEPT, calibration_markdown
    from mi_lidar.cli.calibrate import result_table
    from tests.terminal import WIDTH

    row = {"parameter": "sensor.range_bias", "values": 180, "unit": "m", "mean_before": 0.0, "mean_after": 0.036}
    summary = {"steps_run": 230, "stopped_early": True, "effects": [], "warnings": []}
    nll = {"initial": 9.2763, "counting": 4.5964, "shared_start": 3.7888}
    kept = calibration_markdown({**summary, "held_out_nll": {**nll, "fitted": 3.7888}}, [row], "t")
    beaten = calibration_markdown({**summary, "held_out_nll": {**nll, "fitted": 3.70}}, [row], "t")
    assert SHARED_KEPT in kept and SHARED_KEPT not in beaten
    bias = np.full(180, 0.036)
    result = SimpleNamespace(
        names=["sensor.range_bias"],
        initial={"sensor.range_bias": bias * 0},
        fitted={"sensor.range_bias": bias},
        steps_run=230,
        stopped_early=True,
        initial_nll=9.2763,
        counting_nll=4.5964,
        shared={"sensor.range_bias": 0.036},
        shared_nll=3.7888,
        fitted_nll=3.7888,
    )
    console = Console(width=WIDTH, record=True)
    console.print(result_table(result))
    assert " ".join(SHARED_KEPT.split()) in " ".join(console.export_text().split())
