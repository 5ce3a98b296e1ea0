"""``mi-lidar fit-sensor``: fit a learned sensor model (return density) to a log in its scene.

The log's rays are split into training and held-out rays (alternate scans, or alternate column
blocks of a single scan, as ``diagnose`` does) and traced once in the scene. Then, for the chosen
family of :mod:`mi_lidar.core.densities`:

* ``np-reg`` and ``p-reg`` are estimated in closed form from the element state of every training ray
  (:class:`~mi_lidar.core.densities.samples.StateSamples`), conditioned on range, incidence, label
  and, where that scores better held out, beam; their bandwidths chosen by the held-out NLL of the
  one likelihood (:func:`fit_learned_density`). Each return is first credited to the ray's first
  element; in scenes with permeable elements each ray's outcome is then credited anew under the fitted
  density, both shared among the elements that could have produced it by their posterior and wholly to
  the most likely one, and the density refitted on whichever scores better held out, while that gains
  (an EM over the pass-through mixture: a wall's back face, a second leaf);
* ``beam`` and ``physics`` are fitted by the one Adam fitter on the training rays.

Every figure is reported on the held-out rays, beside the scene's own model: the NLL (nats per ray,
the one score) and the realism of samples drawn from each model at the same rays (median and p90
|range error| against the measurement, hit/miss F1, histogram match), so that a model that wins the
NLL by spreading its mass is caught at once. The fitted density is saved as a ``.npz`` that a scene
references as ``<string name="density" value="np_reg(file=sensor.npz)"/>``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import drjit as dr
import numpy as np

from mi_lidar.core.densities import BeamDensity, PhysicsDensity
from mi_lidar.core.densities.histogram import fit_np_reg
from mi_lidar.core.densities.preg import fit_p_reg
from mi_lidar.core.densities.samples import StateSamples, protocol_residual_edges
from mi_lidar.core.densities.tables import StateGrid
from mi_lidar.core.effects.base import FootprintEffect
from mi_lidar.core.elements import ElementTable
from mi_lidar.core.likelihood import element_shares
from mi_lidar.core.log import Log
from mi_lidar.core.metrics import metrics_of
from mi_lidar.core.params import choose_names
from mi_lidar.core.problem import Problem, fit_parts
from mi_lidar.core.rays import LogRays
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.loop.compare import simulate_log_rays
from mi_lidar.loop.split import split_rays

FAMILIES = ("np-reg", "p-reg", "beam", "physics")
MAX_LABEL_GROUPS = 16  # labels a learned density keeps apart (higher labels share the last group)
MAX_TABLE_ENTRIES = 20_000_000  # NP-Reg states x residual bins beyond which beams stay pooled (~75 B each at peak)
CREDIT_ROUNDS = 8  # EM rounds of the learned densities in scenes with permeable elements (at most)
CREDIT_GAIN = 0.01  # nats per ray: the crediting rounds stop once a round gains less held out
LEAST_SHARE = 1e-6  # shares of an outcome at most this are left out of the fit (Intel wall map: 4 rows in 5, NLL alike)
CHOSEN_SETTINGS = {
    "np-reg": ("h_ranges", "h_incidences", "uniforms", "reaches", "h_nulls"),
    "p-reg": ("h_ranges", "h_incidences", "escapes"),
}


@dataclass
class SensorFit:
    """Result of :func:`fit_sensor`.

    Attributes:
        family: the fitted family.
        model: the scene's sensor model with the fitted density.
        rows: per model (the scene's, the fitted one), held-out NLL and sample metrics.
        candidates: bandwidth candidates and their held-out NLL (learned families).
        train_rays, test_rays: rays used.
        warnings: what makes the fit doubtful (e.g. :func:`~mi_lidar.scene.sensor_check.scene_warnings`).
    """

    family: str
    model: SensorModel
    rows: list = field(default_factory=list)
    candidates: list = field(default_factory=list)
    train_rays: int = 0
    test_rays: int = 0
    warnings: list = field(default_factory=list)

    @property
    def density(self):
        return self.model.density


def default_grid(
    samples: StateSamples, n_labels: int, range_step: float = 1.0, incidence_step: float = 10.0
) -> StateGrid:
    """A fine state grid for a log: ranges every ``range_step`` m to the farthest nominal range,
    incidence every ``incidence_step`` deg (plus the unknown bin), labels kept apart, beams pooled
    (:func:`fit_learned_density` decides whether to keep them apart)."""
    far = float(np.nanmax(samples.nominal)) if np.any(samples.met) else 10.0
    edges = list(np.arange(0.0, far + range_step, range_step)) + [1.0e9]
    return StateGrid(
        range_edges=[float(e) for e in edges],
        incidence_edges=[float(e) for e in np.arange(0.0, 90.0 + 1e-9, incidence_step)],
        n_labels=label_groups(n_labels),
    )


def label_groups(n_labels: int) -> int:
    """Labels a learned density keeps apart: at most :data:`MAX_LABEL_GROUPS` (higher labels share the last)."""
    return max(1, min(n_labels, MAX_LABEL_GROUPS))


CREDITS = ("first", "shares", "most likely")  # traced_states: which elements a ray's outcome is credited to


def traced_states(problem: Problem, model: SensorModel, credit: str = "first") -> StateSamples:
    """The element state of every ray of ``problem`` (traced under ``model``) and its measurement.

    ``credit`` (:data:`CREDITS`) says which element's state: the ray's first; ``"shares"``: the ray's outcome
    shared among the elements it met and the escape state by the posterior under ``model`` that each produced
    it, one weighted sample per share (the E step of an EM); ``"most likely"``: the element of the largest
    share, whole (the hard EM's) (:meth:`~mi_lidar.core.likelihood.ElementShares.credited`; what an effect's
    virtual elements, e.g. outliers, explain is left out). When ``model`` fans beams out into sub-rays (a
    footprint effect), the first element along each beam's axis (its sub-ray 0).
    """
    problem.trace(model)
    label = np.asarray(problem.table.label)
    parts = []
    for chunk in problem.chunks:
        z, hit = np.asarray(chunk.z, np.float64), np.asarray(chunk.hit)
        if chunk.rounds.width != z.size:  # sub-ray j of beam i in lane j n + i (FootprintEffect.footprint)
            copies = chunk.rounds.width // z.size
            beam = np.tile(np.asarray(chunk.rays.beam), copies)
            axis = StateSamples.from_rounds(chunk.rounds, beam, label, np.tile(z, copies), np.tile(hit, copies))
            parts.append(axis.take(np.arange(z.size)))
            continue
        credited = None
        if credit != "first":
            with dr.suspend_grad():
                shares = element_shares(problem.table, model, chunk.rays, chunk.rounds, chunk.z, chunk.hit)
            credited = shares.credited(most_likely=credit == "most likely", least=LEAST_SHARE)
        parts.append(StateSamples.from_rounds(chunk.rounds, np.asarray(chunk.rays.beam), label, z, hit, credited))
    return StateSamples(
        *(np.concatenate([getattr(p, f.name) for p in parts]) for f in dataclasses.fields(StateSamples))
    )


def fit_sensor(
    log: Log,
    scene,
    family: str = "np-reg",
    max_train: int = 400_000,
    max_test: int = 200_000,
    steps: int = 200,
    seed: int = 0,
    pool_labels: bool = False,
    progress=None,
    force: bool = False,
) -> SensorFit:
    """Fit a return density of ``family`` to ``log`` in ``scene`` (see the module docstring).

    Args:
        log: measured log.
        scene: loaded Mitsuba scene or scene XML path.
        family: one of :data:`FAMILIES`.
        max_train, max_test: rays per split (random subsample beyond).
        steps: Adam steps for the parametric families.
        seed: subsampling and sampling seed.
        pool_labels: the learned densities ignore the element labels (NP-Reg: one histogram per range
            and incidence; P-Reg: one regression), so the density means the same in scenes whose labels
            name other classes.
        progress: optional ``progress(message)``.
        force: fit even when the log's sensor does not match the scene's
            (:func:`~mi_lidar.scene.sensor_check.check_log_sensor`).
    """
    from mi_lidar.scene.loading import scene_sensor_model
    from mi_lidar.scene.sensor_check import log_scene, scene_warnings

    (family,) = choose_names([family], FAMILIES, "fit-sensor: unknown model")  # np_reg, NP-Reg or np-reg
    say = progress or (lambda message: None)
    scene = log_scene(log, scene, force=force)
    base = scene_sensor_model(scene)[0]
    rays = LogRays.from_log(log, scene=scene)
    train_index, test_index = split_rays(log, max_train, max_test, seed)
    table = ElementTable.from_scene(scene)
    train, test = Problem.build(scene, rays, train_index, table), Problem.build(scene, rays, test_index, table)
    samples = traced_states(train, base)
    say(f"traced {train.n:,} training and {test.n:,} held-out rays")
    result = SensorFit(family=family, model=base, train_rays=train.n, test_rays=test.n)
    result.warnings = scene_warnings(test.near_surface(base), rays.hit[test_index])

    def held_out(density) -> float:
        return test.nll(dataclasses.replace(base, density=density))

    n_labels = 1 if pool_labels else int(np.asarray(table.label).max()) + 1
    density, result.candidates = fit_density(
        family, base, samples, held_out, n_labels, train, steps, credit=crediting(train, base)
    )
    model = dataclasses.replace(base, density=density)
    say(f"fitted {family}")
    result.model = model
    for name, candidate in (("scene model", base), (f"{family} fitted", model)):
        result.rows.append(
            {
                "model": name,
                "train_nll": train.nll(candidate),
                **sample_metrics(scene, table, rays, test, candidate, seed),
            }
        )
    return result


def crediting(problem: Problem, base: SensorModel):
    """``credit(density) -> [StateSamples, ...]``: ``problem``'s rays credited under ``base`` with ``density``,
    once per way of :data:`CREDITS` after the first (:func:`traced_states`); or None when every element of
    the scene is opaque (then a return comes from the ray's first element) or when ``base`` fans beams out
    into sub-rays (a footprint effect: the trace then holds sub-rays, and a return is a blend of theirs,
    not one element's)."""
    opaque = bool(np.all(np.asarray(problem.table.p_hit) >= 1.0))
    if opaque or any(isinstance(effect, FootprintEffect) for effect in base.effects):
        return None

    def credit(density) -> list[StateSamples]:
        model = dataclasses.replace(base, density=density)
        return [traced_states(problem, model, credit) for credit in CREDITS[1:]]

    return credit


def fit_density(
    family: str,
    base: SensorModel,
    samples: StateSamples,
    held_out,
    n_labels: int,
    train: Problem,
    steps: int,
    credit=None,
    **options,
) -> tuple:
    """A density of ``family`` fitted to training states (learned families) or rays (parametric ones).

    Args:
        family: one of :data:`FAMILIES`.
        base: the model whose density is replaced (its maximum range bounds the learned densities).
        samples: the first element of every training ray (:func:`traced_states`).
        credit: optional ``credit(density) -> [StateSamples, ...]``: the same rays credited to the elements
            that produced their outcomes under ``density``, each way (:func:`crediting`), for the EM of the
            learned families.
        held_out: ``held_out(density) -> NLL`` (nats per ray) on rays not in ``samples``, which picks
            the bandwidths of the learned families.
        n_labels: class labels of the scene.
        train: the training rays (the parametric families are fitted on them by the one fitter).
        steps: Adam steps of the parametric families.
        **options: candidate bandwidths of the learned families (``h_ranges``, ``h_incidences``).

    Returns:
        The density and its bandwidth table (empty for the parametric families).
    """
    if family in ("np-reg", "p-reg"):
        return fit_learned_density(family, base, samples, held_out, n_labels, credit=credit, **options)
    density = BeamDensity(z_max=base.max_range) if family == "beam" else PhysicsDensity()
    fit_parts(dataclasses.replace(base, density=density), train, [density], steps=steps)
    return density, []


def fit_learned_density(
    family: str, base: SensorModel, samples: StateSamples, held_out, n_labels: int, credit=None, **options
) -> tuple:
    """NP-Reg or P-Reg conditioned on range, incidence, label and, where the held-out rays say so, beam.

    The bandwidths are chosen with the beams pooled; on a log of several beams the chosen setting is
    then fitted again with every beam kept apart (each beam's law shrunk to its label's) and kept only
    when it scores better held out, so a sensor whose beams differ (per-laser bias, noise or dropout)
    gets per-beam laws and one whose beams agree is not fragmented. NP-Reg keeps beams pooled when its
    tables would exceed :data:`MAX_TABLE_ENTRIES`.

    With ``credit`` (see :func:`fit_density`), between the two: up to :data:`CREDIT_ROUNDS` rounds of
    crediting every training ray's outcome under the current density, shared by the posterior (the E step
    of an EM) and wholly to the most likely element (a hard EM's), refitting on each with the chosen
    bandwidths and keeping the refit that scores better held out, each round kept only when it scores
    better than the last, until one gains less than :data:`CREDIT_GAIN`. Neither way wins everywhere: the
    shares on the Ouster frame's ``fit-scene`` scene (NP-Reg 6.311 -> 6.116, 6.092, 6.087 nats per ray, where
    the most likely alone gave 6.104), the most likely element on the Intel wall map, whose cells' two
    faces 5 cm apart blur a table that takes both their shares (NP-Reg 3.648 -> 2.868, 2.813, 2.807, where the
    shares alone gave 2.817; P-Reg 4.215 -> 3.115, 2.853, 2.812, then the shares 2.8075).

    Returns:
        The density and its candidate table: rows ``(*bandwidths, beams, held-out NLL)``, the rows of the
        crediting rounds after the bandwidth search's.
    """
    grid = default_grid(samples, n_labels)
    z_max = base.max_range

    def fit(states: StateSamples, n_beams: int, **setting):
        chosen = {**options, **setting}
        if family == "np-reg":
            return fit_np_reg(states, dataclasses.replace(grid, n_beams=n_beams), held_out, z_max=z_max, **chosen)
        return fit_p_reg(states, held_out, z_max=z_max, n_labels=label_groups(n_labels), n_beams=n_beams, **chosen)

    density, rows = fit(samples, 1)
    table = [(*row[:-1], 1, row[-1]) for row in rows]
    best = min(table, key=lambda row: row[-1])
    best_setting = {name: (value,) for name, value in zip(CHOSEN_SETTINGS[family], best)}
    for _ in range(CREDIT_ROUNDS if credit is not None else 0):
        trials = [(states, *fit(states, 1, **best_setting)) for states in credit(density)]
        credited, refitted, rows = min(trials, key=lambda trial: trial[2][0][-1])
        table.append((*rows[0][:-1], 1, rows[0][-1]))
        if rows[0][-1] >= best[-1]:
            break
        gain = best[-1] - rows[0][-1]
        density, samples, best = refitted, credited, table[-1]
        if gain < CREDIT_GAIN:
            break
    n_beams = int(samples.beam.max()) + 1 if samples.n else 1
    bins = len(options.get("edges", protocol_residual_edges(z_max)))
    if n_beams == 1 or (family == "np-reg" and grid.size * n_beams * bins > MAX_TABLE_ENTRIES):
        return density, table
    apart, rows = fit(samples, n_beams, **best_setting)
    table.append((*rows[0][:-1], n_beams, rows[0][-1]))
    return (apart, table) if rows[0][-1] < best[-1] else (density, table)


def sample_metrics(scene, table, rays: LogRays, problem: Problem, model: SensorModel, seed: int) -> dict:
    """Held-out NLL and the realism of one sampled scan at the held-out rays (see :func:`metrics_of`)."""
    sim_range, sim_hit = simulate_log_rays(scene, table, rays, model, seed, index=problem.index)
    return metrics_of(
        problem.log_likelihood(model), rays.measured[problem.index], rays.hit[problem.index], sim_range, sim_hit
    )


def save_sensor(result: SensorFit, path: str | Path) -> Path:
    """Write the fitted density to ``path`` with the fit's figures as notes."""
    notes = {
        "family": result.family,
        "rows": result.rows,
        "candidates": result.candidates,
        "train_rays": result.train_rays,
        "test_rays": result.test_rays,
    }
    return result.density.save(path, notes=notes)
