"""Fitting scene and sensor parameters to a log: counting start, shared start, then Adam on the likelihood.

The loss is the mean negative scored log-likelihood per ray (nats): the one likelihood of
:mod:`mi_lidar.core.likelihood` with its one floor, so the NLLs calibration prints are those of
``compare`` and ``diagnose``. The rays of the log are split once into a training part and a
held-out part; every step draws a mini-batch of training rays from a generator seeded by
``(seed, step)``, and the held-out loss is evaluated every ``eval_every`` steps for early stopping
(the best held-out parameters are kept). The steps are those of the one fitter,
:func:`mi_lidar.core.fitting.adam_fit`.

The likelihood is evaluated on compact trace records (:mod:`mi_lidar.core.trace`):
only the (ray, element) pairs that exist, round by round. How much is computed once depends on
what is fitted:

* nothing moves rays or geometry (hit probabilities, range sigmas, range bias and scale, effects
  that do not perturb rays): every ray of the log is traced once and each element's return
  distribution along it computed once; a step only gathers the fitted per-element values and
  evaluates the mixture;
* an effect that perturbs rays is fitted: the trace is reused, the segments' geometry is rebuilt
  along the perturbed rays at every step (gradients through the rays);
* geometry is fitted (heights, centers, scales, beam angles, extrinsics): the scene is updated and
  each mini-batch re-traced at every step.

Per-beam parameters that start equal on every beam (a range bias or beam angle offset at identity)
are first fitted as one value shared by all beams, with everything else selected (the *shared
start*), and the per-beam fit starts from there. A beam that sees little (an upward beam of a
spinning Lidar meets only a few tree crowns) otherwise settles on a local optimum near its start:
an ellipsoid's return is confined to its chord, so a bias a few centimetres off puts returns
outside it, where the floor flattens the loss. On the README's off-road drive (true bias 5 cm on
every beam) two such beams ended at -1.8 and -1.4 cm from 0; from the shared 4.9 cm they keep it.

While ellipsoid centers or scales are fitted, the training loss is the smoothed surrogate of
:mod:`~mi_lidar.core.smoothing` (annealed to the exact model, learning rates shrinking with
it); the held-out loss is always exact.
"""

from __future__ import annotations

import fnmatch
import math
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.calibration.parameters import P_EPS, ParameterSpace
from mi_lidar.calibration.result import FitResult, no_gain_warnings
from mi_lidar.core.arrays import aligned
from mi_lidar.core.effects.base import Effect
from mi_lidar.core.errors import CalibrationError, ParameterError
from mi_lidar.core.fitting import adam_fit, constant_schedule
from mi_lidar.core.likelihood import mixture_log_likelihood, round_segment, score
from mi_lidar.core.log import Log
from mi_lidar.core.metrics import metrics_of
from mi_lidar.core.problem import Problem, moves_rays
from mi_lidar.core.rays import LogRays
from mi_lidar.core.segment import ELLIPSOID, Segment
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.core.smoothing import smoothing_at
from mi_lidar.core.trace import CachedBatch, RayCache, cache_distributions, trace_rounds
from mi_lidar.scene.loading import scene_sensor_model
from mi_lidar.scene.sensor_check import check_log_sensor, scene_warnings


@dataclass
class FitOptions:
    """Settings of a calibration run.

    Attributes:
        steps: maximum Adam steps.
        batch_size: training rays per step (all of them when the log is smaller).
        holdout: fraction of the rays held out for validation, in (0, 1).
        eval_every: steps between held-out evaluations.
        eval_rays: at most this many held-out rays are evaluated.
        patience: stop after this many held-out evaluations without improvement.
        seed: seed of the split and of the per-step mini-batch draws.
        learning_rates: ``{glob: lr}`` overrides of the default learning rates (first match wins).
        lr_scale: factor applied to every learning rate.
        counting_start: start hit probabilities from the counting estimate.
        shared_start: fit per-beam parameters that start equal on every beam as one shared value
            first (see the module docstring).
        gate: a return within ``gate`` range sigmas of a surface element counts as its hit.
        smoothing, smoothing_final: while ellipsoid centers or scales are fitted, the training
            loss smooths ellipsoids by this many sigmas of the element, annealed geometrically
            over ``steps`` (:mod:`~mi_lidar.core.smoothing`); 0 trains on the exact
            likelihood. The held-out loss is always exact.
    """

    steps: int = 200
    batch_size: int = 1 << 16
    holdout: float = 0.2
    eval_every: int = 10
    eval_rays: int = 1 << 18
    patience: int = 5
    seed: int = 0
    learning_rates: dict = field(default_factory=dict)
    lr_scale: float = 1.0
    counting_start: bool = True
    shared_start: bool = True
    gate: float = 3.0
    smoothing: float = 0.1
    smoothing_final: float = 0.01


def returned_and_passed(seg: Segment, z: mi.Float, hit: mi.Bool, gate: float) -> tuple[mi.Bool, mi.Bool]:
    """Counting rule of one element: did it return the measured range, or let the ray pass?

    A return counts as the element's when ``z`` lies in its chord (ellipsoids) or within ``gate``
    sigmas of its mean (surfaces); the ray passed the element when it missed or returned beyond.
    """
    ellipsoid = seg.kind == ELLIPSOID
    upper = dr.select(ellipsoid, seg.hi, seg.mean + gate * seg.sigma)
    lower = dr.select(ellipsoid, seg.lo, seg.mean - gate * seg.sigma)
    returned = hit & (z >= lower) & (z <= upper)
    return returned, ~returned & (~hit | (z > upper))


class Calibration:
    """One calibration problem: a scene, a log, and the parameters selected by globs.

    Args:
        scene: the loaded Mitsuba scene (its geometry is updated while fitting geometry).
        log: the measured log.
        globs: parameter globs (see :mod:`mi_lidar.calibration.parameters`).
        model: the sensor model to start from (default: the scene's).
        options: fitting settings.
        pattern: the firing pattern of the log's sensor when it is not the scene sensor's (e.g.
            :func:`~mi_lidar.core.patterns.from_log.pattern_from_log` of a planar log); the log
            is checked against it, and per-beam parameters follow its beams.
        force: fit even when the log's sensor does not match (see
            :func:`~mi_lidar.scene.sensor_check.check_log_sensor`).

    Raises:
        CalibrationError: a glob matches nothing.
        SensorMismatchError: the log's sensor is not the scene's (or ``pattern``).
    """

    def __init__(
        self,
        scene,
        log: Log,
        globs: list[str],
        model: SensorModel | None = None,
        options: FitOptions | None = None,
        pattern=None,
        force: bool = False,
    ):
        check_log_sensor(log, scene, pattern, force)
        self.options = options or FitOptions()
        if not 0 < self.options.holdout < 1:
            raise CalibrationError(f"holdout={self.options.holdout} must lie in (0, 1), e.g. 0.2")
        for what, rate in [("lr_scale", self.options.lr_scale), *self.options.learning_rates.items()]:
            if not 0 < rate < math.inf:
                raise CalibrationError(
                    f"{what}={rate}: learning rates and their factor lr_scale must be finite numbers > 0, e.g. "
                    "lr_scale=0.1 for smaller steps"
                )
        if not (self.options.smoothing == 0 or self.options.smoothing >= self.options.smoothing_final > 0):
            raise CalibrationError(
                f"smoothing={self.options.smoothing}, smoothing_final={self.options.smoothing_final}: "
                "use smoothing=0 (exact likelihood) or smoothing >= smoothing_final > 0 (sigmas), "
                "e.g. 0.1 and 0.01"
            )
        self.scene = scene
        base_model = model or scene_sensor_model(scene)[0]
        self.space = ParameterSpace(scene, base_model, n_beams=log.shape[1])
        self.names = self.space.select(globs)
        self.model = self.space.calibration_model(self.names)
        self.params = {n: self.space.params[n] for n in self.names}
        self.geometric = any(p.geometric for p in self.params.values())
        self.smoothed = self.options.smoothing > 0 and any(
            p.family in ("centers", "scales") for p in self.params.values()
        )
        self.static = not (self.geometric or moves_rays(self.model))  # segment distributions computed once
        edits = any(
            type(e).modify_segment is not Effect.modify_segment
            or type(e).likelihood_segment is not Effect.likelihood_segment
            for e in self.model.effects
        )
        # only hit probabilities move: the densities of the measured ranges are computed once too
        self.densities = self.static and not edits and all(p.family == "p_hit" for p in self.params.values())
        self.rays = LogRays.from_log(log, relative_time=False, scene=scene)
        order = np.random.default_rng(self.options.seed).permutation(self.rays.n)
        n_held = max(1, int(round(self.options.holdout * self.rays.n)))
        self.held_out = np.sort(order[:n_held][: self.options.eval_rays])
        self.train = np.sort(order[n_held:])
        self._cache: dict[str, RayCache] = {}
        self._part_rays: dict[str, tuple] = {}
        self.observations: dict[str, np.ndarray] = {}

    # --------------------------------------------------------------------- likelihood
    def _records(self, part: str, position: np.ndarray, values: dict, smoothing: float = 0.0):
        """The rays at ``position`` in part ``part`` (``"train"`` or ``"held_out"``) with their records.

        The part's rays are uploaded once and gathered per batch. Without fitted geometry the
        records come from the part's :class:`RayCache` (traced once): a :class:`CachedBatch` when
        the return distributions are cached (:attr:`static`), else compact :class:`Rounds`. With
        fitted geometry the scene takes the detached ``values`` and the rays are traced anew, with
        the margin of ellipsoid ``smoothing`` (sigmas) when it is > 0.

        Returns:
            ``(rays, measured ranges (m), hits, records)`` of the batch.
        """
        if part not in self._part_rays:
            self._part_rays[part] = self.rays.batch(self.train if part == "train" else self.held_out)
        all_rays, all_z, all_hit = self._part_rays[part]
        lanes = mi.UInt32(aligned(np.asarray(position).astype(np.uint32)))
        rays, z, hit = all_rays.take(lanes), dr.gather(mi.Float, all_z, lanes), dr.gather(mi.Bool, all_hit, lanes)
        if self.geometric:
            with dr.suspend_grad():
                table, model = self.space.build({k: dr.detach(v) for k, v in values.items()}, self.model)
                table = table.replaced(smoothing=smoothing)
                self.space.push_geometry(table)
                return rays, z, hit, trace_rounds(self.scene, table, model, rays)
        if part not in self._cache:
            with dr.suspend_grad():
                table, model = self.space.build({}, self.model)
                rounds = trace_rounds(self.scene, table, model, all_rays)
                if self.static:
                    measured = dr.select(all_hit, all_z, 0.0) if self.densities else None
                    rounds = cache_distributions(rounds, table, model, all_rays, measured)
                self._cache[part] = RayCache.from_rounds(rounds)
        cache = self._cache[part]
        return rays, z, hit, cache.batch(position) if self.static else cache.select(position)

    def log_likelihood(self, values: dict, rays, z, hit, rounds, smoothing: float = 0.0) -> mi.Float:
        """Per-ray scored log-likelihood (nats) under natural parameter ``values`` (keeps gradients).

        ``smoothing`` > 0 (sigmas) scores ellipsoids with the fitting-only surrogate of
        :mod:`~mi_lidar.core.smoothing` (the records must be traced with the same smoothing).
        """
        table, model = self.space.build(values, self.model)
        table = table.replaced(smoothing=smoothing)
        return score(mixture_log_likelihood(table, model, rays, rounds, z, hit), hit)

    def held_out_loss(self, values: dict) -> float:
        """Mean negative log-likelihood per held-out ray (nats) under natural ``values``."""
        total, size = 0.0, self.options.batch_size
        with dr.suspend_grad():
            for first in range(0, len(self.held_out), size):
                position = np.arange(first, min(first + size, len(self.held_out)))
                rays, z, hit, rounds = self._records("held_out", position, values)
                total += float(dr.sum(-self.log_likelihood(values, rays, z, hit, rounds))[0])
        return total / len(self.held_out)

    def held_out_samples(self, values: dict, seed: int = 0) -> dict:
        """The held-out NLL beside the realism of a scan sampled at the held-out rays under natural ``values``.

        Returns:
            :func:`~mi_lidar.core.metrics.metrics_of` of the held-out rays (Chamfer distance included).
        """
        parts: dict[str, list] = {k: [] for k in ("ll", "z", "hit", "range", "sim_hit", "origin", "direction")}
        size = self.options.batch_size
        with dr.suspend_grad():
            table, model = self.space.build(values, self.model)
            if self.geometric:
                self.space.push_geometry(table)
            for first in range(0, len(self.held_out), size):
                position = np.arange(first, min(first + size, len(self.held_out)))
                rays, z, hit, rounds = self._records("held_out", position, values)
                sim = model.simulate_rays(self.scene, table, rays, seed)
                for key, value in (
                    ("ll", self.log_likelihood(values, rays, z, hit, rounds)),
                    ("z", z),
                    ("hit", hit),
                    ("range", sim["range"]),
                    ("sim_hit", sim["hit"]),
                    ("origin", np.asarray(rays.origin).T),  # (3, B) -> (B, 3)
                    ("direction", np.asarray(rays.direction).T),
                ):
                    parts[key].append(np.asarray(value))
        a = {k: np.concatenate(v) for k, v in parts.items()}
        return metrics_of(a["ll"], a["z"], a["hit"], a["range"], a["sim_hit"], a["origin"], a["direction"])

    # ------------------------------------------------------------------ counting start
    def counting_estimate(self, values: dict) -> dict[str, np.ndarray]:
        """Closed-form hit probabilities ``hits / (hits + pass-throughs)`` per element (thesis).

        A ray's return is attributed to the first element it met whose return distribution
        covers the measured range (within ``gate`` sigmas for surfaces, inside the chord for
        ellipsoids); the elements met before it, and every element met by a missing ray, count
        a pass-through. Elements no training ray met keep their values.

        Returns:
            New natural values of the selected ``elements.*.p_hit`` parameters; the number of
            training rays that met each of their elements is left in :attr:`observations`.
        """
        n = self.space.table.n_elements
        hits, passes = dr.zeros(mi.Float, n), dr.zeros(mi.Float, n)
        size = self.options.batch_size
        with dr.suspend_grad():
            table, model = self.space.build(values, self.model)
            for first in range(0, len(self.train), size):
                position = np.arange(first, min(first + size, len(self.train)))
                rays, z, hit, rounds = self._records("train", position, values)
                rounds = rounds.rounds() if isinstance(rounds, CachedBatch) else rounds
                rays = model.prepare_rays(rays)
                done = dr.zeros(mi.Bool, rounds.width)  # the ray's return is already attributed
                for r in rounds.rounds:
                    seg, _ = round_segment(table, model, rays, r)
                    done = dr.gather(mi.Bool, done, r.prev)
                    returned, passed = returned_and_passed(
                        seg, dr.gather(mi.Float, z, r.ray), dr.gather(mi.Bool, hit, r.ray), self.options.gate
                    )
                    returned, passed = returned & ~done, passed & ~done
                    dr.scatter_reduce(dr.ReduceOp.Add, hits, 1.0, r.element, returned)
                    dr.scatter_reduce(dr.ReduceOp.Add, passes, 1.0, r.element, passed)
                    done = done | returned
                    dr.eval(hits, passes, done)
        hits, passes = np.asarray(hits), np.asarray(passes)
        out = {}
        for name, par in self.params.items():
            if par.family != "p_hit":
                continue
            index = np.asarray(par.target[1])
            seen = hits[index] + passes[index]
            self.observations[name] = seen
            current = np.asarray(values[name]) if name in values else par.initial
            estimate = np.where(seen > 0, hits[index] / np.maximum(seen, 1), current)
            out[name] = np.clip(estimate, P_EPS, 1 - P_EPS)
        return out

    # ------------------------------------------------------------------------- fitting
    def learning_rate(self, name: str) -> float:
        """Learning rate of parameter ``name``: the first matching override, else its default, times ``lr_scale``."""
        rate = next(
            (lr for glob, lr in self.options.learning_rates.items() if fnmatch.fnmatchcase(name, glob)),
            self.params[name].lr,
        )
        return float(rate) * self.options.lr_scale

    def tied_names(self, natural: dict) -> list[str]:
        """The selected per-beam parameters whose values in ``natural`` are equal on every beam (the shared start's)."""
        return [
            n
            for n, par in self.params.items()
            if par.per_beam and par.initial.size > 1 and np.ptp(np.asarray(natural[n])) == 0
        ]

    def _adam(self, natural: dict, tied: list[str], progress, offset: int, total: int):
        """Adam from ``natural`` values, each ``tied`` parameter as one value shared by its beams; the
        :class:`~mi_lidar.core.fitting.FitResult` of :func:`~mi_lidar.core.fitting.adam_fit` (steps
        reported to ``progress`` after ``offset`` earlier ones, out of ``total``)."""
        opts = self.options
        variables = [
            par.variable(np.asarray(natural[name])[: 1 if name in tied else None], self.learning_rate(name))
            for name, par in self.params.items()
        ]

        def schedule(step: int, steps: int) -> float:
            """Steps shrink with the smoothing, so the fit settles as the surrogate sharpens."""
            if not self.smoothed:
                return constant_schedule(step, steps)
            return math.sqrt(smoothing_at(step, steps, opts.smoothing, opts.smoothing_final) / opts.smoothing)

        def objective(values, step: int) -> float:
            # ---------------- Mini-batch of training rays, seeded by (seed, step) ----------------
            if opts.batch_size >= len(self.train):
                position = np.arange(len(self.train))
            else:
                position = np.random.default_rng((opts.seed, step)).integers(0, len(self.train), opts.batch_size)
            kappa = smoothing_at(step - 1, opts.steps, opts.smoothing, opts.smoothing_final) if self.smoothed else 0.0
            current = values()
            rays, z, hit, rounds = self._records("train", position, current, kappa)
            loss = -dr.mean(self.log_likelihood(current, rays, z, hit, rounds, kappa))
            dr.backward(loss)
            return float(loss[0])

        def report(step: int, steps: int, train: float, held: float) -> None:
            if progress is not None:
                progress(offset + step, total, train, held)

        try:
            return adam_fit(
                variables,
                objective,
                opts.steps,
                lr=1.0,
                schedule=schedule,
                evaluate=self.held_out_loss,
                eval_every=opts.eval_every,
                patience=opts.patience,
                progress=report,
            )
        except ParameterError as exc:
            raise CalibrationError(
                f"{exc}; lower the learning rates (--lr-scale 0.1) and check that the log's ranges are in metres"
            ) from exc

    def fit(self, progress=None) -> FitResult:
        """Run the counting start, the shared start and Adam with early stopping; see the module docstring.

        Args:
            progress: optional callable ``progress(step, total_steps, train_loss, held_out_loss)``
                (held-out loss NaN between evaluations). ``total_steps`` is the most steps the fit can take,
                the same in every call: ``steps``, twice that with a shared start, whose steps come first (the
                per-beam fit counts on from where it stopped); an early stop ends short of it.

        Raises:
            CalibrationError: the loss or a gradient becomes non-finite.
        """
        opts = self.options
        initial = {n: p.initial.copy() for n, p in self.params.items()}
        natural = {n: mi.Float(p.initial.astype(np.float32)) for n, p in self.params.items()}
        initial_nll = self.held_out_loss(natural)
        samples = {"initial": self.held_out_samples(natural)}
        counting = self.counting_estimate(natural) if opts.counting_start else {}
        natural.update({n: mi.Float(v.astype(np.float32)) for n, v in counting.items()})
        counting_nll = self.held_out_loss(natural) if counting else initial_nll
        shared, shared_nll, done, history = {}, counting_nll, 0, []
        tied = self.tied_names(natural) if opts.shared_start else []
        total = opts.steps * (2 if tied else 1)
        if tied:
            first = self._adam(natural, tied, progress, offset=0, total=total)
            natural.update({n: mi.Float(v.astype(np.float32)) for n, v in first.values.items()})
            shared = {n: float(first.values[n][0]) for n in tied}
            natural.update({n: mi.Float(np.full(self.params[n].initial.size, shared[n], np.float32)) for n in tied})
            shared_nll, done, history = first.best_loss, first.steps_run, first.history
        result = self._adam(natural, [], progress, offset=done, total=total)
        history += [(done + step, *losses) for step, *losses in result.history[1 if history else 0 :]]
        fitted = result.values
        final = {n: mi.Float(v.astype(np.float32)) for n, v in fitted.items()}
        table, model = self.space.build(final, self.model)
        samples["fitted"] = self.held_out_samples(final)
        if self.geometric:
            self.space.push_geometry(table)
        on_surface = Problem.build(self.scene, self.rays, self.held_out).near_surface(model)
        return FitResult(
            names=list(self.names),
            initial=initial,
            counting=counting,
            fitted=fitted,
            observations=dict(self.observations),
            history=history,
            initial_nll=initial_nll,
            counting_nll=counting_nll,
            fitted_nll=result.best_loss,
            stopped_early=result.stopped_early,
            steps_run=done + result.steps_run,
            table=table,
            model=model,
            shared=shared,
            shared_nll=shared_nll,
            shared_steps=done,
            samples=samples,
            warnings=scene_warnings(on_surface, self.rays.hit[self.held_out])
            + no_gain_warnings(initial_nll, counting_nll, result.best_loss),
        )
