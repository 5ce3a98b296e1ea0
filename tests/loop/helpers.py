"""Shared set-up of the loop tests: bundled scenes, synthetic logs with hidden effects, fitting."""

from __future__ import annotations

import dataclasses

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.core.effects import parse_effects
from mi_lidar.core.problem import Problem, fit_parts
from mi_lidar.core.rays import LogRays
from mi_lidar.loop.catalog import candidate
from mi_lidar.scene.loading import load_scene, scene_sensor_model
from mi_lidar.scene.simulation import simulate

from ..conftest import SCENES


def room(n_scans: int = 30, seed: int = 0):
    """The indoor planar scene, its sensor model and ``n_scans`` random poses inside the room."""
    scene = load_scene(SCENES / "indoor_planar.xml")
    model, pose = scene_sensor_model(scene)
    rng = np.random.default_rng(seed)
    poses = np.repeat(pose[None], n_scans, 0)
    poses[:, 0, 3] += rng.uniform(-3, 3, n_scans)
    poses[:, 1, 3] += rng.uniform(-2, 2, n_scans)
    return scene, model, poses


def street(n_scans: int = 2, seed: int = 0):
    """The urban street scene (VLP-16), its sensor model and ``n_scans`` poses along the street."""
    scene = load_scene(SCENES / "urban_street.xml")
    model, pose = scene_sensor_model(scene)
    poses = np.repeat(pose[None], n_scans, 0)
    poses[:, 0, 3] += np.linspace(-4, 4, n_scans)
    return scene, model, poses


def hidden_log(scene, model, poses, hidden: str, seed: int = 1):
    """A log simulated with the effects ``hidden`` added to ``model``; returns (log, true model)."""
    true = dataclasses.replace(model, effects=model.effects + parse_effects(hidden))
    return simulate(scene, poses=poses, model=true, seed=seed), true


def diagnose_hidden_bias(tmp_path, *candidates: str):
    """``mi-lidar diagnose`` (80 columns) of a room log with a hidden 5 cm range bias, trying ``candidates``.

    Returns:
        The CLI result and the report folder (``tmp_path / "d"``).
    """
    from tests.terminal import invoke_at_80

    scene, model, poses = room(6)
    log, _ = hidden_log(scene, model, poses, "range_bias(bias=0.05)")
    log.save(tmp_path / "room.npz")
    out = tmp_path / "d"
    chosen = [arg for name in candidates for arg in ("--candidate", name)]
    return invoke_at_80(["diagnose", tmp_path / "room.npz", SCENES / "indoor_planar.xml", "--out", out, *chosen]), out


def first_kept(log, clean) -> np.ndarray:
    """(S, B, F) True where ``log`` returned the element that ``clean`` (same rays and seed, no dropout) met first."""
    return log.hit & (log.attributes["element_id"] == clean.attributes["element_id"])


def assert_keep_law(scene, model, poses, hidden: str, clean: str, attribute: str, bins, law) -> None:
    """Assert that a dropout ``hidden`` keeps the first element at the rate ``law`` of a clean-log ``attribute``.

    Args:
        hidden, clean: the effects of the log with the dropout and of the log without it (same seed).
        attribute: the clean log's attribute the law reads (``cos_incidence``, ``nominal_range``).
        bins: ``(lo, hi)`` ranges of the attribute; in each, among the clean log's hits, the share
            whose first element still returns must be the mean of ``law(attribute)`` within 3
            binomial sigma + 0.02.
        law: the keep probability, a function of (n,) attribute values.
    """
    log, _ = hidden_log(scene, model, poses, hidden)
    reference, _ = hidden_log(scene, model, poses, clean)
    x = reference.attributes[attribute][reference.hit]
    kept = first_kept(log, reference)[reference.hit]
    for lo, hi in bins:
        m = (x >= lo) & (x < hi)
        expect = np.mean(law(x[m]))
        assert abs(kept[m].mean() - expect) < 3 * np.sqrt(expect * (1 - expect) / m.sum()) + 0.02


def recover(scene, model, log, name: str, steps: int = 120, **start):
    """Fit effect ``name`` (from its fitting start) on ``log``; return the fitted effect and model."""
    effect = candidate(name, log.shape[1], 8, **start)
    fitted = dataclasses.replace(model, effects=model.effects + [effect])
    rays = LogRays.from_log(log)
    fit_parts(fitted, Problem.build(scene, rays), [effect], steps=steps)
    return effect, fitted


def mean_ll(scene, model, log) -> float:
    """Mean log-likelihood per ray (nats) of ``log`` under ``model``."""
    rays = LogRays.from_log(log)
    return float(Problem.build(scene, rays).log_likelihood(model).mean())


def finite_difference_check(scene, model, log, effect, key: str, h: float, n_rays: int = 2000):
    """(autodiff, central finite difference) of the summed log-likelihood w.r.t. ``effect[key]``."""
    rays = LogRays.from_log(log)
    problem = Problem.build(scene, rays, np.arange(min(n_rays, rays.n)))
    problem.trace(model)
    value = float(np.asarray(effect.params[key])[0])

    def total(v, grad=False):
        effect.params[key] = mi.Float(v)
        if grad:
            dr.enable_grad(effect.params[key])
        ll = dr.sum(problem.chunk_log_likelihood(model, problem.chunks[0]))
        if grad:
            dr.backward(ll)
            return float(dr.grad(effect.params[key])[0])
        return float(ll[0])

    auto = total(value, grad=True)
    numeric = (total(value + h) - total(value - h)) / (2 * h)
    effect.params[key] = mi.Float(value)
    return auto, numeric
