"""Candidate effects for diagnosis: every registered effect, started where fitting can move it.

An effect class may declare, besides its :class:`~mi_lidar.core.effects.ParamSpec` defaults:

* ``fit_start``: starting values for fitting (``{name: value}``), used where the default sits on a
  boundary with no gradient (a dropout probability of exactly 0, say);
* ``fit_scales``: the typical size of each parameter (the fitter's step unit);
* ``fit_exclude``: parameters that stay fixed (a sweep period, say);
* ``per_label``: parameters holding one value per class label.
"""

from __future__ import annotations

from mi_lidar.core.effects.base import EFFECTS, Effect
from mi_lidar.loop.fit import widen

# Effects that describe the scene or sensor setup rather than a measurable deviation: not offered
# as diagnosis candidates unless asked for by name.
NOT_CANDIDATES = ("extrinsics",)

# Fitting hints for catalog effects that do not carry their own (effect name -> hints).
HINTS = {
    "range_noise": {"fit_start": {"sigma0": 0.002, "k": 1e-4}, "fit_scales": {"sigma0": 0.005, "k": 0.001}},
    "range_bias": {"fit_scales": {"bias": 0.01}},
    "range_scale": {"fit_scales": {"scale": 0.002}},
    "beam_offsets": {"fit_scales": {"elevation": 0.002, "azimuth": 0.002}},
}


def candidate(name: str, n_beams: int, n_labels: int, **values) -> Effect:
    """Instantiate effect ``name`` at its fitting start, widened to the log's beams and labels.

    Args:
        name: catalog name.
        n_beams: beams (rows) of the log.
        n_labels: class labels of the scene.
        **values: overrides of the starting values.
    """
    cls = EFFECTS[name]
    hints = HINTS.get(name, {})
    start = {**hints.get("fit_start", {}), **getattr(cls, "fit_start", {}), **values}
    options = {k: v for k, v in start.items() if k in cls.options}
    params = {k: v for k, v in start.items() if k in cls.specs}
    effect = widen(cls(**options, **params), n_beams, n_labels)
    if "fit_scales" in hints and not hasattr(cls, "fit_scales"):
        effect.fit_scales = hints["fit_scales"]
    return effect


def variants(name: str) -> list[dict]:
    """Option settings to try for effect ``name``: one per choice of its first option."""
    options = EFFECTS[name].options
    if not options:
        return [{}]
    key, choices = next(iter(options.items()))
    return [{key: choice} for choice in choices]


def candidate_names(present: list[Effect], include: list[str] | None = None) -> list[str]:
    """Registered effects not yet in the model (``include`` restricts and orders them)."""
    have = {e.name for e in present}
    names = include if include is not None else [n for n in sorted(EFFECTS) if n not in NOT_CANDIDATES]
    return [n for n in names if n not in have]
