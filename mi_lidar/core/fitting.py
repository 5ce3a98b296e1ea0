"""The one fitter: Adam over Dr.Jit on named parameter arrays, with bounds, transforms and step units.

Every fit in mi-lidar (effect parameters in ``diagnose``, scene and sensor parameters in
``calibrate``, density parameters, the planar benchmark's models) runs :func:`adam_fit`:

* each :class:`FitVariable` is optimised in its own units: ``raw = T(x)`` with ``T`` the identity,
  ``log`` or ``logit`` (:attr:`FitVariable.transform`), and Adam moves ``u`` in
  ``raw = T(x0) + scale * u``, so one learning rate suits parameters of very different sizes (a
  noise sigma of millimetres and a dropout exponent of units);
* after every step each variable is projected back into its bounds (projected Adam), so the loss is
  only ever evaluated at admissible values;
* the caller's ``objective`` builds the loss from the current values (as many chunks as it likes,
  calling ``dr.backward`` on each) and returns its total; an optional ``evaluate`` scores held-out
  data every ``eval_every`` steps for early stopping;
* the result holds the best values seen (lowest held-out loss when ``evaluate`` is given, else
  lowest training loss), so a refit never ends worse than its start;
* with a ``tolerance``, a fit stops once its best loss has improved by less than that over the last
  ``window`` steps (a screening fit that has converged, or that finds nothing to fit, stops
  instead of running out its steps).

Kernel reuse: the starting values and scales enter kernels as opaque arrays (64-byte aligned), so one
compiled kernel serves every step of a fit and every fit of the same code.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.core.arrays import aligned
from mi_lidar.core.errors import ParameterError

TRANSFORMS = ("value", "log", "logit")
OPEN_EDGE = 1e-6  # a log or logit variable starting on 0 (or 1), where T is infinite, starts this far inside


def _forward(transform: str, x: np.ndarray) -> np.ndarray:
    """``T(x)`` in numpy (float64)."""
    x = np.asarray(x, np.float64)
    with np.errstate(divide="ignore"):
        if transform == "log":
            return np.log(x)
        if transform == "logit":
            return np.log(x) - np.log1p(-x)
    return x


def _inverse(transform: str, raw: mi.Float) -> mi.Float:
    """``T^-1(raw)`` in Dr.Jit (keeps gradients)."""
    if transform == "log":
        return dr.exp(raw)
    if transform == "logit":
        return 1.0 / (1.0 + dr.exp(-raw))
    return raw


@dataclass
class FitVariable:
    """One fitted array.

    Attributes:
        name: its name (in results and messages).
        initial: (n,) starting natural values.
        lower, upper: bounds of the natural values (kept after every step).
        scale: step unit in transformed units: Adam's steps are about ``lr * scale``.
        transform: ``"value"``, ``"log"`` or ``"logit"``; starting values where ``T`` is infinite (0 for
            both, 1 for the logit) start :data:`OPEN_EDGE` inside.
    """

    name: str
    initial: np.ndarray
    lower: float = -np.inf
    upper: float = np.inf
    scale: float = 0.1
    transform: str = "value"

    def __post_init__(self):
        if self.transform not in TRANSFORMS:
            raise ParameterError(f"fit variable {self.name!r}: transform {self.transform!r}; use one of {TRANSFORMS}")
        if not self.scale > 0:
            raise ParameterError(f"fit variable {self.name!r}: scale={self.scale} must be > 0")
        initial = np.atleast_1d(np.asarray(self.initial, np.float64))
        if not np.all(np.isfinite(initial)):
            raise ParameterError(f"fit variable {self.name!r}: starting values must be finite")
        initial = np.clip(initial, self.lower, self.upper)
        if self.transform != "value":
            initial = np.clip(initial, OPEN_EDGE, 1.0 - OPEN_EDGE if self.transform == "logit" else np.inf)
        self.initial = initial
        lo, hi = _forward(self.transform, np.array([self.lower, self.upper]))
        self._raw_bounds = (max(float(lo), -1e30), min(float(hi), 1e30))
        self._raw0 = mi.Float(aligned(_forward(self.transform, self.initial).astype(np.float32)))
        self._scale = mi.Float(aligned(np.full(self.initial.size, self.scale, np.float32)))
        dr.make_opaque(self._raw0, self._scale)

    @property
    def size(self) -> int:
        return int(self.initial.size)

    def natural(self, u: mi.Float) -> mi.Float:
        """Natural values at optimiser state ``u`` (keeps gradients)."""
        return _inverse(self.transform, self._raw0 + self._scale * u)

    def project(self, u: mi.Float) -> mi.Float:
        """The optimiser state moved back so that the values lie within the bounds."""
        raw = dr.clip(dr.detach(self._raw0 + self._scale * u), *self._raw_bounds)
        return (raw - dr.detach(self._raw0)) / dr.detach(self._scale)

    def state_of(self, natural: np.ndarray) -> mi.Float:
        """The optimiser state of natural values ``natural`` (numpy)."""
        raw = _forward(self.transform, np.clip(np.asarray(natural, np.float64), self.lower, self.upper))
        return mi.Float(aligned(((raw - _forward(self.transform, self.initial)) / self.scale).astype(np.float32)))


@dataclass
class FitResult:
    """Outcome of :func:`adam_fit`.

    Attributes:
        values: best natural values per variable name (numpy).
        history: rows ``(step, training loss, held-out loss or NaN)``.
        best_loss: the loss the best values were chosen by (held-out when evaluated, else training).
        steps_run: Adam steps taken.
        stopped_early: the held-out loss stopped improving before the last step.
    """

    values: dict[str, np.ndarray]
    history: list = field(default_factory=list)
    best_loss: float = math.inf
    steps_run: int = 0
    stopped_early: bool = False


def stalled(best: list[float], tolerance: float | None, window: int, min_steps: int) -> bool:
    """True when the best loss ``best[-1]`` improved by less than ``tolerance`` over the last ``window`` steps.

    Args:
        best: best training loss after each step so far (non-increasing).
        tolerance: the improvement that counts, in the loss's units (None: never stalled).
        window: steps looked back.
        min_steps: steps taken before a fit may stop.
    """
    if tolerance is None or len(best) < max(min_steps, window + 1):
        return False
    return best[-1 - window] - best[-1] < tolerance


def cosine_schedule(step: int, steps: int) -> float:
    """Learning-rate factor decaying from 1 to 0.1 along a half cosine."""
    return 0.1 + 0.45 * (1.0 + math.cos(math.pi * step / max(steps, 1)))


def fine_cosine_schedule(step: int, steps: int) -> float:
    """Learning-rate factor decaying from 1 to 0.01 along a half cosine (fits whose optimum is sharp)."""
    return 0.01 + 0.495 * (1.0 + math.cos(math.pi * step / max(steps, 1)))


def constant_schedule(step: int, steps: int) -> float:
    """Learning-rate factor 1 at every step."""
    return 1.0


def adam_fit(
    variables: list[FitVariable],
    objective: Callable[[Callable[[], dict[str, mi.Float]], int], float],
    steps: int,
    lr: float = 0.3,
    schedule: Callable[[int, int], float] = cosine_schedule,
    evaluate: Callable[[dict[str, mi.Float]], float] | None = None,
    eval_every: int = 10,
    patience: int | None = None,
    progress: Callable[[int, int, float, float], None] | None = None,
    tolerance: float | None = None,
    window: int = 15,
    min_steps: int = 20,
) -> FitResult:
    """Minimise ``objective`` over ``variables`` with projected Adam.

    Args:
        variables: the fitted arrays.
        objective: ``objective(values, step) -> total loss``: ``values()`` returns a fresh dict of
            natural values (Dr.Jit arrays with gradients; call it once per chunk, since backward
            releases the graph), and the objective calls ``dr.backward`` on each piece of the loss.
        steps: Adam steps.
        lr: learning rate in units of each variable's ``scale``.
        schedule: ``schedule(step, steps)`` -> factor on ``lr``.
        evaluate: optional held-out loss of natural values (no gradients), for early stopping and
            the choice of the best values.
        eval_every: steps between held-out evaluations (and after the last step).
        patience: stop after this many held-out evaluations without improvement (None: never).
        progress: optional ``progress(step, steps, training loss, held-out loss or NaN)``.
        tolerance: stop once the best loss (held-out when ``evaluate`` is given, else training)
            improved by less than this over the last ``window`` steps, after at least ``min_steps``
            steps (:func:`stalled`; None: run every step).
        window, min_steps: see ``tolerance``.

    Returns:
        The :class:`FitResult` (best values, history).

    Raises:
        ParameterError: the loss or a gradient is not finite (the message says which variables).
    """
    if not variables:
        return FitResult(values={})
    opt = mi.ad.Adam(lr=lr)
    for v in variables:
        opt[v.name] = dr.zeros(mi.Float, v.size)

    def values() -> dict[str, mi.Float]:
        return {v.name: v.natural(opt[v.name]) for v in variables}

    def snapshot() -> dict[str, np.ndarray]:
        with dr.suspend_grad():
            return {v.name: np.asarray(v.natural(dr.detach(opt[v.name])), np.float64) for v in variables}

    best = FitResult(values=snapshot())
    if evaluate is not None:
        with dr.suspend_grad():
            best.best_loss = float(evaluate({v.name: v.natural(dr.detach(opt[v.name])) for v in variables}))
        best.history.append((0, math.nan, best.best_loss))
    stale, step = 0, 0
    trail: list[float] = []  # best training loss after each step
    for step in range(1, steps + 1):
        opt.set_learning_rate(lr * schedule(step - 1, steps))
        current = snapshot() if evaluate is None else {}
        total = float(objective(values, step))
        bad = [v.name for v in variables if not np.all(np.isfinite(np.asarray(dr.grad(opt[v.name]))))]
        if not math.isfinite(total) or bad:
            raise ParameterError(
                f"fit step {step}: the loss is {total:g} and the gradients of {bad or 'no variable'} are not "
                "finite; check that the log's ranges are in metres and the scene is the one the log was "
                "recorded in, or lower the learning rate"
            )
        if evaluate is None and total < best.best_loss:
            best.values, best.best_loss = current, total
        opt.step()
        for v in variables:
            opt[v.name] = v.project(opt[v.name])
        held = math.nan
        if evaluate is not None and (step % eval_every == 0 or step == steps):
            with dr.suspend_grad():
                held = float(evaluate({v.name: v.natural(dr.detach(opt[v.name])) for v in variables}))
            if held < best.best_loss - 1e-9:
                best.values, best.best_loss, stale = snapshot(), held, 0
            else:
                stale += 1
        best.history.append((step, total, held))
        trail.append(best.best_loss if evaluate is not None else min(total, trail[-1]) if trail else total)
        if progress is not None:
            progress(step, steps, total, held)
        if (patience is not None and stale >= patience) or stalled(trail, tolerance, window, min_steps):
            best.stopped_early = True
            break
    best.steps_run = step
    return best
