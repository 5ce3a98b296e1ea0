"""Named, validated, fittable parameters: the one declaration shared by effects and return densities.

A :class:`ParamSpec` says everything about one parameter: default, unit, meaning, bounds, whether
it holds one value per beam or per class label, and how the fitter treats it (kept fixed or fitted,
starting value, step unit, transform, lower bound while fitting). A :class:`Parametrized` object
(an :class:`~mi_lidar.core.effects.base.Effect` or a
:class:`~mi_lidar.core.densities.base.ReturnDensity`) declares its specs and string options as class
attributes and holds its values as Dr.Jit arrays in :attr:`Parametrized.params`, so that
``dr.enable_grad`` on them makes the model differentiable in them.

Example::

    class RangeOffset(Effect):
        name = "range_offset"
        specs = {"offset": ParamSpec(0.0, "m", "added to every return", lower=-5, upper=5, fit_scale=0.01)}
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.core.arrays import aligned
from mi_lidar.core.errors import MiLidarError, ParameterError
from mi_lidar.core.fitting import lookup
from mi_lidar.core.frames import MAX_COORDINATE_M

MAX_DISTANCE_M = MAX_COORDINATE_M  # ranges and range windows (m): beyond 1e8 m a value is a misread number
MAX_SIGMA_M = 1e3  # range noise (m): the longest-reaching Lidars reach a few km and spread returns by centimetres to
# decimetres; a sigma beyond a kilometre spreads a return over the whole range window, so it is a misread number


@dataclass(frozen=True)
class ParamSpec:
    """Declaration of one parameter.

    Attributes:
        default: default value (scalar) or None when the parameter is required.
        unit: physical unit, for documentation and reports.
        doc: one-line meaning.
        lower, upper: allowed closed range (checked on construction, kept while fitting).
        per_beam: the parameter holds one value per beam (a list in XML).
        per_label: the parameter holds one value per class label.
        fit: False for a parameter that fitting keeps fixed (a sweep period, an interval end).
        fit_start: value fitting starts from when the default sits where the likelihood has no
            gradient (a dropout probability of exactly 0, say); None: start from the current value.
        fit_scale: the parameter's typical size, the fitter's step unit (a number, or a function of
            the owning object for sizes that depend on an option), in the units of ``fit_transform``.
        fit_transform: the units the fitter moves the parameter in: ``"value"``, ``"log"`` or ``"logit"``
            (:class:`~mi_lidar.core.fitting.FitVariable`). A probability whose values span orders of
            magnitude (a dropout of 2 % on one label and of 95 % on another) is fitted as a logit: a
            step of fixed size in value units takes 2 % to the bound 0 at once, where a lost return's
            likelihood is floored and the fit cannot come back.
        fit_lower: lower bound kept while fitting, when above ``lower``: a scale whose variance is
            quadratic in it (a noise sigma) has zero gradient at 0, so an optimizer that reaches 0
            would stay there whatever the data say.
        only: ``{option: (choices...)}``: the parameter exists only under these option choices
            (e.g. the logistic law's angle); otherwise it is ignored, not fitted and not printed.
    """

    default: float | None
    unit: str
    doc: str
    lower: float = -np.inf
    upper: float = np.inf
    per_beam: bool = False
    per_label: bool = False
    fit: bool = True
    fit_start: float | None = None
    fit_scale: float | Callable[[Any], float] = 0.1
    fit_transform: str = "value"
    fit_lower: float | None = None
    only: dict = field(default_factory=dict)

    @property
    def fit_bound(self) -> float:
        """The lower bound of fitted values: ``fit_lower`` if set, else ``lower``."""
        return self.lower if self.fit_lower is None else max(self.lower, self.fit_lower)


class Parametrized:
    """Base of objects with named parameters (:class:`ParamSpec`) and string options.

    Class attributes:
        name: catalog name (used in XML, on the command line and in reports).
        specs: parameter declarations.
        options: ``{option: (choice, ...)}``; the first choice is the default.
        variant_options: options whose choices ``diagnose`` tries as separate candidates.
    """

    name: ClassVar[str] = ""
    kind: ClassVar[str] = "object"
    specs: ClassVar[dict[str, ParamSpec]] = {}
    options: ClassVar[dict[str, tuple[str, ...]]] = {}
    variant_options: ClassVar[tuple[str, ...]] = ()

    def __init__(self, **values):
        unknown = sorted(set(values) - set(self.specs) - set(self.options))
        if unknown:
            allowed = sorted(set(self.specs) | set(self.options))
            raise ParameterError(f"{self.kind} {self.name!r}: unknown parameter(s) {unknown}; allowed: {allowed}")
        self.choices: dict[str, str] = {}
        for key, allowed_choices in self.options.items():
            choice = str(values.get(key, allowed_choices[0]))
            if choice not in allowed_choices:
                raise ParameterError(
                    f"{self.kind} {self.name!r}: {key}={choice!r}; choose one of {list(allowed_choices)}"
                )
            self.choices[key] = choice
        self.params: dict[str, mi.Float] = {}
        for key, spec in self.specs.items():
            raw = values.get(key, spec.default)
            if raw is None:
                raise ParameterError(
                    f"{self.kind} {self.name!r}: parameter {key!r} ({spec.doc}, {spec.unit}) is required"
                )
            try:
                array = np.atleast_1d(np.asarray(raw, dtype=np.float64))
            except ValueError:
                raise ParameterError(
                    f"{self.kind} {self.name!r}: {key}={raw!r} is not a number ({spec.doc}, {spec.unit})"
                ) from None
            bad = ~np.isfinite(array) | (array < spec.lower) | (array > spec.upper)
            if np.any(bad):  # an infinite bound is open: inf itself is refused
                low, high = "[" if np.isfinite(spec.lower) else "(", "]" if np.isfinite(spec.upper) else ")"
                raise ParameterError(
                    f"{self.kind} {self.name!r}: {key}={array[bad][0]:g} {spec.unit} is outside "
                    f"{low}{spec.lower:g}, {spec.upper:g}{high} ({spec.doc})"
                )
            self.params[key] = mi.Float(array.astype(np.float32))

    def __getitem__(self, key: str) -> mi.Float:
        return self.params[key]

    def active(self, key: str) -> bool:
        """True when parameter ``key`` exists under the current option choices (:attr:`ParamSpec.only`)."""
        return all(self.choices.get(option) in allowed for option, allowed in self.specs[key].only.items())

    def fitted_names(self) -> list[str]:
        """Names of the parameters that fitting changes (active and not fixed)."""
        return [k for k, spec in self.specs.items() if spec.fit and self.active(k)]

    def fit_scale(self, key: str) -> float:
        """The step unit of parameter ``key`` (:attr:`ParamSpec.fit_scale`)."""
        scale = self.specs[key].fit_scale
        return float(scale(self) if callable(scale) else scale)

    def per_beam(self, key: str, beam: mi.UInt32) -> mi.Float:
        """Value of per-beam parameter ``key`` for each lane's beam (the last value repeats).

        Read by :func:`~mi_lidar.core.fitting.lookup`, so its gradient in a fit is the same in every run.
        """
        values = self.params[key]
        return lookup(values, dr.minimum(beam, dr.width(values) - 1))

    def per_label(self, key: str, label: mi.UInt32) -> mi.Float:
        """Value of per-label parameter ``key`` for each lane's label (the last value repeats).

        Read by :func:`~mi_lidar.core.fitting.lookup`, so its gradient in a fit is the same in every run.
        """
        values = self.params[key]
        return lookup(values, dr.minimum(label, dr.width(values) - 1))

    def parameters(self) -> dict[str, mi.Float]:
        """Named parameters (Dr.Jit arrays) for traversal and fitting."""
        return self.params

    def widen(self, n_beams: int, n_labels: int) -> Parametrized:
        """Give per-beam parameters ``n_beams`` values and per-label ones ``n_labels`` (in place)."""
        for key, spec in self.specs.items():
            size = n_beams if spec.per_beam else n_labels if spec.per_label else 1
            values = np.asarray(self.params[key])
            if values.size == 1 and size > 1:
                self.params[key] = mi.Float(aligned(np.full(size, values[0], np.float32)))
        return self

    def at_fit_start(self) -> Parametrized:
        """Move parameters that declare a ``fit_start`` there (in place), so that fitting has a gradient."""
        for key, spec in self.specs.items():
            if spec.fit_start is not None and self.active(key):
                size = dr.width(self.params[key])
                self.params[key] = mi.Float(aligned(np.full(size, spec.fit_start, np.float32)))
        return self

    def named_values(self) -> dict:
        """``{option: choice, parameter: value}``: the option choices, then every active parameter as a float (one
        value) or an (n,) numpy array (per beam or per label), in the units of its spec."""
        active = {key: np.asarray(value, np.float64) for key, value in self.params.items() if self.active(key)}
        return self.choices | {key: float(a[0]) if a.size == 1 else a for key, a in active.items()}

    def describe(self) -> str:
        """``name(key=value, ...)``: the object as written in XML or on the command line."""
        parts = [f"{k}={v}" for k, v in self.choices.items()]
        for key, value in self.params.items():
            if not self.active(key):
                continue
            array = np.asarray(value)
            parts.append(
                f"{key}={array[0]:.6g}" if array.size == 1 else f"{key}=[{' '.join(f'{x:.6g}' for x in array)}]"
            )
        return f"{self.name}({', '.join(parts)})"


class Snapshot:
    """The parameter values of some parts, copied when it is taken: :meth:`restore` puts them back.

    Taken before a fit, it undoes a fit that failed or a step that is not kept::

        saved = Snapshot(model.effects)
        try:
            fit_parts(model, problem, model.effects)
        except FitError:
            saved.restore()
    """

    def __init__(self, parts: list[Parametrized]):
        self.values = [
            (part, {key: np.array(dr.detach(value), np.float32) for key, value in part.params.items()})
            for part in parts
        ]

    def restore(self) -> None:
        """Put the copied values back (in place), as opaque arrays: read from memory, so no new kernel per value."""
        for part, values in self.values:
            for key, value in values.items():
                array = mi.Float(aligned(value))
                dr.make_opaque(array)
                part.params[key] = array


class Catalog(dict):
    """Registered classes of one kind by name (the effect catalog, the density catalog).

    Args:
        what: what the catalog holds, for messages (``"effect"``, ``"return density"``).
    """

    def __init__(self, what: str):
        super().__init__()
        self.what = what

    def register(self, cls):
        """Add ``cls`` under ``cls.name`` (usable as a decorator)."""
        if not cls.name:
            raise ParameterError(f"{self.what} class {cls.__name__} needs a non-empty `name`")
        self[cls.name] = cls
        return cls

    def cls(self, name: str):
        """The class registered as ``name`` (either spelling, :func:`catalog_name`); a ParameterError listing the
        catalog otherwise."""
        if catalog_name(name) not in self:
            raise ParameterError(f"unknown {self.what} {name!r}; the catalog has: {', '.join(sorted(self)) or 'none'}")
        return self[catalog_name(name)]


def catalog_name(name: str) -> str:
    """The catalog's spelling of an effect or density name: ``np-reg`` and ``np_reg`` are both ``np_reg``.

    Catalog names are written with underscores; ``fit-sensor --model`` names its families with dashes,
    so a user may write either anywhere a name is taken.
    """
    return name.strip().replace("-", "_")


def choose_names(given, known: tuple[str, ...], what: str) -> tuple[str, ...]:
    """The names of ``known`` that ``given`` spell, in any case and with ``-`` or ``_``.

    The verbs name their models in two styles (``fit-sensor --model np-reg``, ``benchmark-planar --model
    NP-Reg``); a user who writes one where the other is taken, or ``m0`` for ``M0``, gets the model.

    Args:
        given: the names the user wrote (one or more).
        known: the names taken, as the verb spells them.
        what: the start of the message, e.g. ``"benchmark-planar: unknown models"``.

    Returns:
        ``given`` in ``known``'s spelling, in the given order.

    Raises:
        ParameterError: a name that is none of ``known``, or no name: the message lists ``known``.
    """
    spelled = {catalog_name(name).lower(): name for name in known}
    given = list(given)
    unknown = [name for name in given if catalog_name(name).lower() not in spelled]
    if unknown or not given:
        raise ParameterError(f"{what} {unknown}; choose from {', '.join(known)}")
    return tuple(spelled[catalog_name(name).lower()] for name in given)


def parse_calls(spec: str, make: Callable[..., Any], what: str) -> list:
    """Parse ``"name(key=value, key=[v1 v2]), other(...)"`` into objects built by ``make(name, **values)``.

    This is the syntax of the integrator's ``effects`` and ``density`` properties in XML and of the
    command line. An empty string gives an empty list.

    Args:
        spec: the text.
        make: factory ``make(name, **values)``.
        what: what is parsed, for error messages (``"effects"``, ``"density"``).
    """
    items: list = []
    rest = spec.strip()
    while rest:
        name, sep, tail = rest.partition("(")
        name = name.strip().strip(",;").strip()
        if not sep:
            items.extend(make(n.strip()) for n in name.split(",") if n.strip())
            break
        body, closing, rest = tail.partition(")")
        if not closing:
            raise ParameterError(f"{what} {spec!r}: missing ')' after {name}(")
        values, depth, current = {}, 0, ""
        for char in body + ",":
            depth += char == "["
            depth -= char == "]"
            if char == "," and depth == 0:
                if current.strip():
                    key, eq, value = current.partition("=")
                    if not eq:
                        raise ParameterError(f"{what} {spec!r}: expected key=value in {current.strip()!r}")
                    values[key.strip()] = _parse_value(value)
                current = ""
            else:
                current += char
        items.append(make(name, **values))
        rest = rest.strip().lstrip(",;").strip()
    return items


def _parse_value(text: str):
    text = text.strip()
    if text.startswith("[") and text.endswith("]"):
        items = text[1:-1].replace(",", " ").split()
        try:
            return [float(x) for x in items]
        except ValueError:
            return items  # the object that takes it names the parameter in its error
    try:
        return float(text)
    except ValueError:
        return text


def property_number(props, plugin: str, name: str, default: float, whole: bool = False) -> float:
    """The number of a plugin's XML property: ``<float name="max_range" value="30"/>`` gives 30.0.

    Mitsuba hands on whatever the XML element holds (a ``<string>``, a ``<float>`` where a count belongs);
    ``float()`` or ``int()`` on it failed without naming the property, or truncated 4.5 to 4.

    Args:
        props: The plugin's ``mi.Properties``.
        plugin: The plugin's name in messages (``"lidar sensor"``).
        name: The property.
        default: Its value when the XML does not set it.
        whole: The property is a count or an id: the value must be a whole number (returned as ``int``).

    Raises:
        ParameterError: naming the plugin, the property and the value: not a number, or not a whole one.
    """
    given = props.get(name, default)
    try:
        value = float(given)
    except (TypeError, ValueError):
        kind = "integer" if whole else "float"
        raise ParameterError(
            f'{plugin}: {name}={given!r} is not a number; write <{kind} name="{name}" value="..."/>'
        ) from None
    if not whole:
        return value
    if not value.is_integer():
        raise ParameterError(f'{plugin}: {name}={given!r} is not a whole number; write <integer name="{name}" .../>')
    return int(value)


def check_limit(
    owner: str,
    name: str,
    value: float | np.ndarray,
    upper: float,
    what: str,
    fix: str = "fix the value",
    *,
    unset_nan: bool = False,
    open_end: bool = False,
    error: type[MiLidarError] = ParameterError,
) -> None:
    """Refuse a distance or range noise outside ``[0, upper]`` m (:data:`MAX_DISTANCE_M`, :data:`MAX_SIGMA_M`).

    The one check of these limits: a negative, non-finite or absurdly large value gets one message.

    Args:
        owner: The plugin or object in messages (``"lidar sensor"``, ``"shape 'ground'"``).
        name: The parameter.
        value: Its value (m), or one value per element.
        upper: The largest value allowed (m).
        what: Why larger values are refused, for the message (:data:`DISTANCE_LIMIT`, :data:`SIGMA_LIMIT`).
        fix: What to do.
        unset_nan: NaN means "unset" (an element without its own range noise) and passes.
        open_end: ``inf`` is allowed too (a range window with no far end).
        error: The exception raised (:class:`~mi_lidar.core.errors.SceneError` for a scene's elements).

    Raises:
        ParameterError: (or ``error``) naming the owner, the parameter, the first bad value (and how many values
            are bad when there are several), the allowed range, why, and the fix.
    """
    values = np.atleast_1d(np.asarray(value, dtype=np.float64))
    ok = (values >= 0) & (values <= upper)
    if unset_nan:
        ok |= np.isnan(values)
    if open_end:
        ok |= values == np.inf
    if ok.all():
        return
    bad = values[~ok]
    count = f" ({bad.size} of {values.size} values)" if values.size > 1 else ""
    allowed = f"[0, {upper:g}] m" + (", or inf for no far end" if open_end else "")
    raise error(f"{owner}: {name}={bad[0]:g} m{count} is outside {allowed} ({what}); {fix}")


DISTANCE_LIMIT = f"a distance beyond {MAX_DISTANCE_M:g} m is a misread number"
SIGMA_LIMIT = f"a range noise beyond {MAX_SIGMA_M:g} m is a misread number"
