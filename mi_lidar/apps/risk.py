"""Application-level loss, risk and development paths (thesis ch. 2.3.3-2.3.5).

An application has parameters ``alpha`` with a prior ``p(alpha)`` and an objective ``J(alpha, D)``
(lower is better) on a dataset ``D``. For a simulated dataset ``D_hat`` of the same states:

* the loss ``l(alpha) = |J(alpha, D) - J(alpha, D_hat)|``;
* the risk: the mean of ``l`` over ``M`` draws ``alpha ~ p(alpha)`` (the same draws for every simulator),
  with its standard error over the draws, and the paired difference of two simulators' risks (the mean
  of ``l_a - l_b`` at the same draws) with its standard error: the draws are shared and a stochastic
  application's runs use common random numbers, so the paired error is the one that says which
  simulator is better;
* a development path ``(alpha_i, J(alpha_i, D_hat))``: what a developer tuning on the simulator does,
  here a cyclic coordinate search on the parameters' grids from a first implementation ``alpha_0``
  (try every value of one parameter, keep the best, go on to the next parameter, until a whole cycle
  changes nothing); the same ``alpha_i`` are scored on the real data, which the developer does not see;
* a sweep (thesis fig. 3.20): every source's metrics along the grid of the application's ``sweep``
  parameter, the others at the best real setting found.

The prior of a parameter is uniform over its grid of values (:class:`Parameter`), so a geometric grid
is a log-uniform prior. ``J`` values are memoized by :class:`Objectives` (and cached on disk), so
risk draws, paths and reruns share evaluations.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np

from mi_lidar.core.errors import ParameterError
from mi_lidar.core.strict_json import nan_for_null, write_json

WITHIN = 0.10  # a simulator's pick is good when its real J is within 10 % of the best real J found


@dataclass(frozen=True)
class Parameter:
    """One application parameter and its prior.

    Attributes:
        name: its name.
        values: its grid, ascending; the prior is uniform over these values.
        start: the value of a first implementation (where development starts); one of ``values``.
        unit: its unit ("" when none).
    """

    name: str
    values: tuple[float, ...]
    start: float
    unit: str = ""

    def __post_init__(self):
        if self.start not in self.values or list(self.values) != sorted(self.values):
            raise ParameterError(f"parameter {self.name}: start {self.start} must be one of ascending {self.values}")


class Application(Protocol):
    """What :func:`evaluate_application` needs of an application (``sweep``: optional name of the parameter swept)."""

    name: str
    objective: str
    parameters: tuple[Parameter, ...]

    def evaluate(self, alpha: dict, states, ranges: np.ndarray) -> dict:
        """Metrics of running with ``alpha`` on ``ranges`` (T, N) at ``states``; ``"J"`` is the objective."""
        ...


def alpha_key(alpha: dict) -> str:
    """A stable text key of a parameter setting."""
    return ",".join(f"{k}={alpha[k]:g}" for k in sorted(alpha))


def start_alpha(app: Application) -> dict:
    """The first implementation's setting."""
    return {p.name: p.start for p in app.parameters}


def sample_alphas(app: Application, m: int, seed: int) -> list[dict]:
    """``m`` settings drawn from the prior (independent uniform draws from each parameter's grid)."""
    rng = np.random.default_rng(seed)
    picks = {p.name: rng.integers(0, len(p.values), m) for p in app.parameters}
    return [{p.name: float(p.values[picks[p.name][k]]) for p in app.parameters} for k in range(m)]


def development_path(app: Application, objective: Callable[[dict], float], start: dict, max_cycles: int = 2):
    """Cyclic coordinate search over the parameter grids from ``start`` (see the module docstring).

    Parameter after parameter, every value of its grid is tried with the others fixed, and the best is
    kept when it improves ``objective``; the search stops after a cycle without a move.

    Returns:
        The path: a list of settings, ``start`` first, each better than the one before.
    """
    path, best = [dict(start)], objective(start)
    for _ in range(max_cycles):
        moved = False
        for p in app.parameters:
            current = path[-1]
            tried = [(objective({**current, p.name: float(v)}), {**current, p.name: float(v)}) for v in p.values]
            value, alpha = min(tried, key=lambda row: row[0])
            if value < best - 1e-9 * max(1.0, abs(best)):
                path.append(alpha)
                best, moved = value, True
        if not moved:
            break
    return path


class Objectives:
    """Memoized metrics of (application, source, setting), optionally cached in a JSON file.

    Args:
        states: the states every source shares.
        ranges: ``{source: (T, N) ranges}``.
        path: JSON cache file (read if present; :meth:`save` writes it atomically).
        key: what the cache belongs to (a cache with another key is ignored).
        progress: optional ``progress(label)`` called after each new evaluation.
    """

    def __init__(self, states, ranges: dict, path: Path | None = None, key: str = "", progress=None):
        self.states, self.ranges, self.path, self.key = states, ranges, path, key
        self.progress = progress or (lambda label: None)
        self.values: dict[str, dict] = {}
        self.new = 0
        if path is not None and path.exists():
            stored = json.loads(path.read_text())
            if stored.get("key") == key:
                self.values = nan_for_null(stored["values"])  # null: a metric that was NaN

    def __call__(self, app: Application, source: str, alpha: dict) -> dict:
        name = f"{app.name}|{source}|{alpha_key(alpha)}"
        if name not in self.values:
            self.values[name] = app.evaluate(alpha, self.states, self.ranges[source])
            self.new += 1
            self.progress(name)
            if self.new % 20 == 0:
                self.save()
        return self.values[name]

    def save(self) -> None:
        if self.path is not None:
            write_json(self.path, {"key": self.key, "values": self.values}, indent=None, default=float)


@dataclass
class AppResult:
    """Risk and development paths of one application (see :func:`evaluate_application`).

    Attributes:
        name, objective: the application and its objective's meaning.
        alphas: the ``M`` prior draws.
        J: ``{source: (M,) J at the draws}``.
        risk: ``{simulator: mean loss}``.
        risk_se: ``{simulator: standard error of the risk over the draws}``.
        paired: ``{a: {b: (mean of l_a - l_b, its standard error)}}`` for every two simulators.
        run_se: ``{source: mean over the draws of the standard error of J over its runs}`` (0 when the
            application reports no ``J_runs``).
        sweep: ``{"parameter", "values", "at", "effort", "metrics": {source: [metrics at each value]}}`` (``effort``:
            the application's metric of the cost of a setting, e.g. ICP iterations), or None.
        paths: ``{source: [settings]}`` developed on that source ("real": developed on real data).
        path_J: ``{source: (sim J, real J) along its path}``.
        best_real: the best real J found (over draws and every path), and its setting.
        picks: ``{simulator: {"alpha", "real_J", "sim_J", "within"}}``: the end of each path.
        metrics: ``{source: [metrics at each draw]}`` (every number the application reports).
    """

    name: str
    objective: str
    parameters: list[dict]
    alphas: list[dict]
    J: dict[str, np.ndarray]
    risk: dict[str, float]
    paths: dict[str, list[dict]]
    path_J: dict[str, tuple[list[float], list[float]]]
    best_real: tuple[float, dict]
    picks: dict[str, dict]
    metrics: dict[str, list[dict]] = field(default_factory=dict)
    risk_se: dict[str, float] = field(default_factory=dict)
    paired: dict[str, dict[str, tuple[float, float]]] = field(default_factory=dict)
    run_se: dict[str, float] = field(default_factory=dict)
    sweep: dict | None = None

    def loss(self, source: str) -> np.ndarray:
        """(M,) ``l(alpha_k)`` of a simulator."""
        return np.abs(self.J[source] - self.J["real"])

    def to_json(self) -> dict:
        return {
            "application": self.name,
            "objective": self.objective,
            "parameters": self.parameters,
            "alphas": self.alphas,
            "J": {k: v.tolist() for k, v in self.J.items()},
            "loss": {k: self.loss(k).tolist() for k in self.risk},
            "risk": self.risk,
            "risk_se": self.risk_se,
            "paired_difference": {
                a: {b: {"mean": d, "se": e} for b, (d, e) in row.items()} for a, row in self.paired.items()
            },
            "run_se": self.run_se,
            "sweep": self.sweep,
            "paths": self.paths,
            "path_J": {k: {"simulated": s, "real": r} for k, (s, r) in self.path_J.items()},
            "best_real": {"J": self.best_real[0], "alpha": self.best_real[1]},
            "picks": self.picks,
            "metrics": self.metrics,
        }


def evaluate_application(app: Application, objectives: Objectives, m: int = 16, seed: int = 0) -> AppResult:
    """Risk of every simulator, development paths on every source, and each simulator's pick judged on real data.

    Args:
        app: the application.
        objectives: memoized metrics; its ``ranges`` must hold ``"real"`` and the simulators.
        m: prior draws for the risk.
        seed: seed of the draws.
    """
    sources = list(objectives.ranges)
    if "real" not in sources:
        raise ParameterError(f"evaluate_application: no 'real' source among {sources}")
    simulators = [s for s in sources if s != "real"]
    alphas = sample_alphas(app, m, seed)
    metrics = {s: [objectives(app, s, a) for a in alphas] for s in sources}
    J = {s: np.array([row["J"] for row in metrics[s]]) for s in sources}
    loss = {s: np.abs(J[s] - J["real"]) for s in simulators}
    risk = {s: float(np.mean(loss[s])) for s in simulators}
    start = start_alpha(app)
    paths, path_J = {}, {}
    for s in ["real", *simulators]:
        path = development_path(app, lambda a, s=s: objectives(app, s, a)["J"], start)
        paths[s] = path
        path_J[s] = ([objectives(app, s, a)["J"] for a in path], [objectives(app, "real", a)["J"] for a in path])
    real_seen = [(J["real"][k], alphas[k]) for k in range(m)]
    real_seen += [(j, a) for s in paths for j, a in zip(path_J[s][1], paths[s])]
    best = min(real_seen, key=lambda row: row[0])
    sweep = None
    if getattr(app, "sweep", None):
        parameter = next(p for p in app.parameters if p.name == app.sweep)
        settings = [{**best[1], parameter.name: float(v)} for v in parameter.values]
        swept = {s: [objectives(app, s, a) for a in settings] for s in sources}
        sweep = {
            "parameter": parameter.name,
            "values": list(parameter.values),
            "at": best[1],
            "effort": getattr(app, "effort", None),
            "metrics": swept,
        }
        best = min([best, *((row["J"], a) for row, a in zip(swept["real"], settings))], key=lambda row: row[0])
    picks = {}
    for s in simulators:
        real_J = path_J[s][1][-1]
        picks[s] = {
            "alpha": paths[s][-1],
            "sim_J": path_J[s][0][-1],
            "real_J": real_J,
            "within": bool(real_J <= best[0] + WITHIN * abs(best[0])),
        }
    objectives.save()
    return AppResult(
        name=app.name,
        objective=app.objective,
        parameters=[
            {"name": p.name, "values": list(p.values), "start": p.start, "unit": p.unit} for p in app.parameters
        ],
        alphas=alphas,
        J=J,
        risk=risk,
        paths=paths,
        path_J=path_J,
        best_real=(float(best[0]), best[1]),
        picks=picks,
        metrics=metrics,
        risk_se={s: standard_error(loss[s]) for s in simulators},
        paired={
            a: {b: (float(np.mean(loss[a] - loss[b])), standard_error(loss[a] - loss[b])) for b in simulators if b != a}
            for a in simulators
        },
        run_se={
            s: float(np.mean([standard_error(row.get("J_runs", [row["J"]])) for row in metrics[s]])) for s in sources
        },
        sweep=sweep,
    )


def standard_error(values) -> float:
    """Standard error of the mean of ``values`` (0 for fewer than two)."""
    values = np.asarray(values, np.float64)
    return float(np.std(values, ddof=1) / np.sqrt(values.size)) if values.size > 1 else 0.0
