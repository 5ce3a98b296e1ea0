"""Candidate effects for diagnosis: every registered effect, started where fitting can move it.

An effect's :class:`~mi_lidar.core.params.ParamSpec` declarations carry everything diagnosis needs:
the fitting start (``fit_start``, where the default sits on a boundary with no gradient), the step
unit (``fit_scale``), parameters kept fixed (``fit=False``), and per-beam / per-label widths. Options
listed in the class's ``variant_options`` are tried as separate candidates (each noise law, each
dropout law).
"""

from __future__ import annotations

from mi_lidar.core.effects.base import EFFECTS, Effect


def candidate(name: str, n_beams: int, n_labels: int, **options) -> Effect:
    """Effect ``name`` at its fitting start, widened to the log's beams and labels.

    Args:
        name: catalog name.
        n_beams: beams (rows) of the log.
        n_labels: class labels of the scene.
        **options: option choices (and parameter overrides) of this candidate.
    """
    effect = EFFECTS[name](**options).widen(n_beams, n_labels).at_fit_start()
    for key, value in options.items():
        if key in effect.specs:  # an explicit starting value wins over the spec's fit_start
            effect.params[key] = type(effect.params[key])(value)
    return effect.widen(n_beams, n_labels)


def variants(name: str) -> list[dict]:
    """Option settings to try for effect ``name``: every combination of its ``variant_options``."""
    cls = EFFECTS[name]
    settings: list[dict] = [{}]
    for option in cls.variant_options:
        settings = [{**s, option: choice} for s in settings for choice in cls.options[option]]
    return settings


def candidate_names(present: list[Effect], include: list[str] | None = None) -> list[str]:
    """Registered effects not yet in the model (``include`` restricts and orders them).

    Raises:
        ParameterError: a name of ``include`` is not in the catalog (the message lists it).
    """
    have = {e.name for e in present}
    names = [EFFECTS.cls(n).name for n in include] if include is not None else sorted(EFFECTS)
    return [n for n in names if n not in have]
