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

Bit-reproducible gradients: the same fit gives the same bits in every run (at the same thread count).
Dr.Jit differentiates ``dr.gather`` by a scatter-add, and on the LLVM backend which lanes' float
additions land in which per-thread copy (``dr.ReduceMode.Expand``, the default for small targets)
or in which order (atomics, ``Direct``/``Local``) follows the thread schedule, which changes from run
to run (Dr.Jit's ``dr.reduce`` documentation: "subject to non-deterministic rounding errors"). A
gather of a few fitted values by many lanes (a density's parameters per state) then got gradients
that differed in their last bits, and Adam, which divides by the gradients' size, carried that into
the fitted values (the beam model on Intel: the 4th significant digit). So the values ``values()``
hands the objective are leaves of their own, and a gather of them written as :func:`lookup` is a
per-lane leaf too; after the objective, each lookup's per-lane gradients are summed per value in
64-bit fixed point (integer additions do not depend on their order: :func:`fixed_point_sums`), added to the
leaves' own gradients in a fixed order, and carried through ``T^-1`` to Adam's state. Every
other reduction of the backward pass (a width-1 value broadcast to many lanes, ``dr.sum``,
``dr.mean``) is an evaluated reduction over fixed blocks, which is deterministic. A :func:`lookup` of
an array computed from the values (``calibrate``'s per-element tables, filled by a scatter of the
fitted elements) gets its sums the same way; they are then carried back through that array's own
graph. A plain ``dr.gather`` of fitted values still works, without that guarantee. The cost: two kernel
launches per step and the lanes' gradients stored once; the beam model's fit on Intel (131,040 beams, 150 steps, 16
lookups per step, 2 threads) took 2.05 s instead of 1.72 s.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.core.arrays import aligned
from mi_lidar.core.errors import FitError, ParameterError

TRANSFORMS = ("value", "log", "logit")
FIXED_POINT_BITS = 61  # a fixed-point sum keeps |sum| below 2^61 (Int64)
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


class _Tape:
    """The leaves one objective call was handed and the lookups made from them (see the module docstring)."""

    def __init__(self):
        self.leaves: list[tuple[str, mi.Float]] = []  # (variable, leaf) in the order values() made them
        self.owner: dict[int, str] = {}  # AD index of a leaf -> its variable
        self.lookups: list[tuple[str, mi.UInt32, mi.Bool, mi.Float]] = []  # owner, index, active, lane
        self.lanes: dict[tuple[int, int, int], mi.Float] = {}  # (values, index, active) -> lane
        self.derived: dict[str, mi.Float] = {}  # owner -> an array computed from leaves that lookups read

    def owner_of(self, values: mi.Float) -> str:
        """The owner of ``values`` read by a lookup: a leaf's variable, or a new owner for an array
        computed from the leaves (kept, with its graph, until :meth:`gradients`)."""
        if values.index_ad not in self.owner:
            name = f"derived {len(self.derived)}"
            self.derived[name] = values
            self.owner[values.index_ad] = name
        return self.owner[values.index_ad]

    def leaf(self, name: str, value: mi.Float) -> mi.Float:
        leaf = mi.Float(dr.detach(value))
        dr.enable_grad(leaf)
        if dr.grad_enabled(leaf):  # not inside dr.suspend_grad()
            self.leaves.append((name, leaf))
            self.owner[leaf.index_ad] = name
        return leaf

    def gradients(self, sizes: dict[str, int]) -> dict[str, mi.Float]:
        """Each variable's gradient: its leaves' own, then its lookups' fixed-point sum (one fixed order).

        The sums of an array computed from the leaves are carried back to them first, through the
        array's own graph (elementwise steps and gathers: deterministic), in the order the arrays were read.
        """
        owners = {**sizes, **{name: dr.width(array) for name, array in self.derived.items()}}
        lanes = [dr.grad(lane) for _, _, _, lane in self.lookups]
        groups: dict[str, list] = {name: [] for name in owners}
        for (name, index, active, _), grad in zip(self.lookups, lanes):
            groups[name].append((grad, index, active))
        sums = fixed_point_sums({name: (parts, owners[name]) for name, parts in groups.items() if parts})
        carried = [(array, sums.pop(name)) for name, array in self.derived.items() if name in sums]
        for array, value in carried:
            dr.accum_grad(array, value)
            dr.enqueue(dr.ADMode.Backward, array)
        if carried:
            dr.traverse(dr.ADMode.Backward)  # one pass: arrays that share steps carry through them together
        total = {name: dr.zeros(mi.Float, size) for name, size in sizes.items()}
        for name, leaf in self.leaves:
            total[name] = total[name] + dr.grad(leaf)
        for name, value in sums.items():
            total[name] = total[name] + value
        return total


_TAPE: _Tape | None = None  # the tape of the objective call under way (None: outside adam_fit)


def lookup(values: mi.Float, index: mi.UInt32, active: mi.Bool | bool = True) -> mi.Float:
    """``values[index]`` per lane, like ``dr.gather``, with a bit-reproducible gradient inside :func:`adam_fit`.

    Use it wherever many lanes read fitted values (a density's parameters per state, an effect's
    per label or per beam, a scene's per-element tables): inside a fit, when ``values`` carries
    gradients (one of the arrays ``values()`` handed out, or an array computed from them), the lanes
    are a leaf of their own and the fitter sums their gradients per value in 64-bit fixed point
    (:func:`fixed_point_sums`) after the objective. Anywhere else it is ``dr.gather``.

    Args:
        values: the values (Dr.Jit, may carry gradients).
        index: (N,) the value each lane reads.
        active: lanes that read (the others get 0).
    """
    tape = _TAPE
    if tape is None or not dr.grad_enabled(values):
        return dr.gather(mi.Float, values, index, active)
    active = mi.Bool(active)
    key = (values.index_ad, index.index, active.index)
    if key not in tape.lanes:  # the same read again (a density asked twice) shares its lanes
        lane = dr.gather(mi.Float, dr.detach(values), index, active)
        dr.enable_grad(lane)
        tape.lanes[key] = lane
        tape.lookups.append((tape.owner_of(values), index, active, lane))
    return tape.lanes[key]


def fixed_point_sums(groups: dict[str, tuple[list[tuple[mi.Float, mi.UInt32, mi.Bool]], int]]) -> dict[str, mi.Float]:
    """Scatter-add sums that are the same bits on any thread schedule and thread count.

    Each group ``(parts, size)`` sums the lanes of its parts ``(values, index, active)`` into ``size``
    targets, in 64-bit fixed point: every lane is rounded to a multiple of ``2^(e - s)``, with ``2^e``
    bounding the group's largest ``|value|`` (an atomic maximum, which does not depend on the order
    either) and ``s`` = :data:`FIXED_POINT_BITS` minus the bits of the group's lane count, and added as
    an integer: integer additions do not depend on their order, and no sum can reach ``2^61``. A
    lane's rounding is below ``2^-s`` of the largest value (``2^-40`` for a million lanes), far below
    float32's (a float32 sum rounds every addition to 2^-24 of the running sum). A non-finite value makes
    its group's sums NaN. Two kernel launches per lane count for all groups: the lanes and their
    bounds, then the sums.
    """
    bounds, scales, totals = {}, {}, {}
    for name, (parts, _) in groups.items():
        bounds[name] = dr.zeros(mi.Float, 1)
        for values, _, active in parts:
            magnitude = dr.select(dr.isfinite(values), dr.abs(values), dr.inf)
            dr.scatter_reduce(dr.ReduceOp.Max, bounds[name], magnitude, dr.zeros(mi.UInt32, dr.width(values)), active)
    dr.eval(bounds, [values for parts, _ in groups.values() for values, _, _ in parts])
    for name, (parts, size) in groups.items():
        lanes = sum(dr.width(values) for values, _, _ in parts)
        shift = FIXED_POINT_BITS - max(1, math.ceil(math.log2(max(lanes, 2)))) - 1
        top = mi.Float64(bounds[name])
        scales[name] = dr.exp2(dr.opaque(mi.Float64, shift) - dr.ceil(dr.log2(dr.maximum(top, 1e-30))))
        finite = dr.isfinite(top)
        totals[name] = dr.zeros(mi.Int64, size)
        for values, index, active in parts:
            counts = mi.Int64(dr.round(dr.select(finite, mi.Float64(values) * scales[name], 0.0)))
            dr.scatter_reduce(dr.ReduceOp.Add, totals[name], counts, index, active)
    dr.eval(totals)
    out = {}
    for name in groups:
        finite = dr.isfinite(bounds[name])
        out[name] = dr.select(finite, mi.Float(mi.Float64(totals[name]) / scales[name]), dr.nan)
    return out


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


def natural_gradient(
    variables: list[FitVariable],
    objective: Callable[[Callable[[], dict[str, mi.Float]], int], float],
    step: int = 1,
    state: dict[str, mi.Float] | None = None,
) -> tuple[float, dict[str, mi.Float]]:
    """One call of ``objective`` and its loss's gradient by the variables' natural values, as :func:`adam_fit` sees it.

    ``values()`` hands the objective leaves (one per variable and call); after the objective, each
    variable's gradient is its leaves' own gradients, then the fixed-point sums of its lookups' (:func:`lookup`,
    :func:`fixed_point_sums`), added in a fixed order (see the module docstring).

    Args:
        variables: the fitted arrays.
        objective: as in :func:`adam_fit`.
        step: the step number passed to ``objective``.
        state: optimiser state per variable (default: zeros, the starting values).

    Returns:
        The objective's total and the gradient per variable name (Dr.Jit, detached).
    """
    global _TAPE
    state = state or {v.name: dr.zeros(mi.Float, v.size) for v in variables}
    tape = _Tape()

    def values() -> dict[str, mi.Float]:
        with dr.suspend_grad():
            natural = {v.name: v.natural(state[v.name]) for v in variables}
        return {name: tape.leaf(name, value) for name, value in natural.items()}

    outer, _TAPE = _TAPE, tape
    try:
        total = float(objective(values, step))
    finally:
        _TAPE = outer
    return total, tape.gradients({v.name: v.size for v in variables})


def non_finite_gradient(step: int, loss: float, bad: dict[str, np.ndarray], sizes: dict[str, int]) -> str:
    """The message of a fit whose loss is finite but whose gradient is not, for the values ``bad`` of each variable.

    Args:
        step: the fit step.
        loss: the (finite) loss.
        bad: per variable, the indices of its values whose gradient is NaN or infinite.
        sizes: values per variable.
    """
    where = "; ".join(
        f"{name} at {', '.join(str(i) for i in index[:5])}{' ...' if index.size > 5 else ''}"
        f" ({index.size} of {sizes[name]} values)"
        for name, index in bad.items()
    )
    return (
        f"fit step {step}: the loss is finite ({loss:g}) but its gradient is not (NaN or infinite) for {where}: "
        "the model is not differentiable there on some of these rays (a formula at its singular point, e.g. a "
        "square root, acos or normalisation at 0, such as a ray at exactly normal or grazing incidence), which "
        "is a bug of the effect or density that computes it: leave these parameters out of the fit or start "
        "them elsewhere, and report it with the log and scene"
    )


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
            Read a few values by many lanes with :func:`lookup`, not ``dr.gather``, so that the fit
            is bit-reproducible (see the module docstring).
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
        FitError: the loss or a gradient is not finite (the message says which variables and values).
    """
    if not variables:
        return FitResult(values={})
    opt = mi.ad.Adam(lr=lr)
    for v in variables:
        opt[v.name] = dr.zeros(mi.Float, v.size)

    def run(step: int) -> float:
        """The objective at ``step``, its gradient carried through ``T^-1`` to Adam's state."""
        state = {v.name: dr.detach(opt[v.name]) for v in variables}
        total, gradients = natural_gradient(variables, objective, step, state)
        for v in variables:  # a variable the loss does not depend on (a zero gradient) gets a zero step
            dr.backward(v.natural(opt[v.name]) * gradients[v.name], flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad)
        return total

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
        total = run(step)
        if not math.isfinite(total):
            raise FitError(
                f"fit step {step}: the loss is {total:g}, not finite: the model gives some measured rays no "
                "likelihood at all, or the values left its domain; check that the log's ranges are in metres "
                "and the scene is the one the log was recorded in, or lower the learning rate"
            )
        bad = {v.name: np.asarray(dr.grad(opt[v.name])) for v in variables}
        bad = {name: np.flatnonzero(~np.isfinite(grad)) for name, grad in bad.items()}
        bad = {name: where for name, where in bad.items() if where.size}
        if bad:
            raise FitError(non_finite_gradient(step, total, bad, {v.name: v.size for v in variables}))
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
