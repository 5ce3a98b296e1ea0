"""Catalog-wide test cases: every effect (each variant) and every parametric density, at test values.

The cases are generated from the catalog itself (``EFFECTS``, ``DENSITIES`` and their
:class:`~mi_lidar.core.params.ParamSpec` declarations), so a newly registered effect is checked by
the gradient and sampling tests with no change here. Each case has a *truth* (values a log is
simulated with) and a *trial* (values the likelihood is differentiated at): the spec's fitting start
(or its default moved one step unit into the admissible range), and that plus half a step unit.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

import mi_lidar
from mi_lidar.core.densities import DENSITIES
from mi_lidar.core.effects import EFFECTS
from mi_lidar.core.params import Parametrized
from mi_lidar.core.patterns import get_pattern
from mi_lidar.core.rays import LogRays
from mi_lidar.scene import scene_sensor_model

from ..conftest import SCENES

# Test values where the spec's own would be a poor place to check (the scene is a 20 m street).
OVERRIDES = {"outliers": {"uniform_max": 30.0}}
LEARNED = {name for name, cls in DENSITIES.items() if cls.learned and cls.name != "beam"}


def variants(cls) -> list[dict]:
    """Every combination of the class's ``variant_options`` (one empty dict when it has none)."""
    settings: list[dict] = [{}]
    for option in cls.variant_options:
        settings = [{**s, option: choice} for s in settings for choice in cls.options[option]]
    return settings


def case_ids() -> list[tuple[str, str, dict]]:
    """``(kind, name, options)`` of every effect variant and parametric density."""
    effects = [("effect", name, v) for name in sorted(EFFECTS) for v in variants(EFFECTS[name])]
    densities = [("density", name, {}) for name in sorted(DENSITIES) if name not in LEARNED]
    return effects + densities


def label(case) -> str:
    kind, name, options = case
    return name + "".join(f"-{v}" for v in options.values())


def values_at(part: Parametrized, shift: float, also: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
    """Fitted parameters, and the fixed ones named in ``also``, at their test truth plus ``shift`` step units
    (inside the bounds)."""
    out = {}
    fitted = part.fitted_names()
    for key in fitted + [k for k in also if k not in fitted]:
        spec = part.specs[key]
        base = np.asarray(part.params[key], np.float64)
        scale = part.fit_scale(key)
        start = base if spec.fit_start is None else np.full_like(base, spec.fit_start)
        if np.allclose(start, spec.fit_bound):
            start = start + scale
        out[key] = np.clip(start + shift * scale, spec.fit_bound + 1e-6 * scale, spec.upper - 1e-6 * scale)
    for key, value in OVERRIDES.get(part.name, {}).items():
        out[key] = np.full_like(np.asarray(part.params[key], np.float64), value)
    return out


def make_part(case, shift: float, n_beams: int, n_labels: int, also: tuple[str, ...] = ()) -> Parametrized:
    """The effect or density of ``case`` with its parameters (see :func:`values_at`) at truth + ``shift`` step
    units."""
    kind, name, options = case
    part = (EFFECTS if kind == "effect" else DENSITIES)[name](**options).widen(n_beams, n_labels)
    for key, value in values_at(part, shift, also).items():
        part.params[key] = type(part.params[key])(value.astype(np.float32))
    return part


@functools.lru_cache(maxsize=1)
def street():
    """The bundled street, its sensor model, a small VLP-16 pattern and two poses."""
    scene = mi_lidar.load_scene(SCENES / "urban_street.xml")
    model, pose = scene_sensor_model(scene)
    poses = np.repeat(pose[None], 2, 0)
    poses[1, 0, 3] += 2.0
    return scene, model, get_pattern("vlp16", n_firings=45), poses


def model_with(base, case, part):
    """``base`` with ``part`` as its density or as its one added effect."""
    if case[0] == "density":
        return dataclasses.replace(base, density=part)
    return dataclasses.replace(base, effects=[part])


def simulated(case, seed: int = 3):
    """A log of the street simulated with the case's truth, and its rays."""
    scene, model, pattern, poses = street()
    truth = make_part(case, 0.0, pattern.shape[0], 8)
    log = mi_lidar.simulate(scene, pattern, poses=poses, seed=seed, model=model_with(model, case, truth))
    return log, LogRays.from_log(log)
