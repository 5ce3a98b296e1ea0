"""Training and held-out rays of a log: the split every fit of the loop is judged on.

Rays are split by whole scans (alternate scans), so that a held-out ray never shares a scan, and so
a pose, with a training ray; a log of one scan is split into alternate blocks of 64 columns (or 64
beams when the scan has more beams than columns, as a planar scan of N beams x 1 firing has)
(:func:`split_rays`). :class:`Splits` holds the splits of one log in its scene, each traced once
(diagnose fits, scores and samples them).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mi_lidar.core.elements import ElementTable
from mi_lidar.core.errors import LogFormatError
from mi_lidar.core.log import Log
from mi_lidar.core.metrics import metrics_of
from mi_lidar.core.problem import Problem
from mi_lidar.core.rays import LogRays
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.loop.compare import RayTable, first_elements, simulate_log_rays
from mi_lidar.loop.realism import Realism, realism_warning


def split_rays(log: Log, max_train: int, max_test: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Training and held-out ray indices (into the log's flattened rays), each sorted.

    Each split is subsampled (without replacement, fixed ``seed``) to at most its maximum.

    Raises:
        LogFormatError: one scan too small to hold out a block (65 columns or beams at least).
    """
    s, h, w = log.shape
    scan, beam, column = np.meshgrid(np.arange(s), np.arange(h), np.arange(w), indexing="ij")
    train = (scan.ravel() % 2 == 0) if s > 1 else (((column if w >= h else beam).ravel() // 64) % 2 == 0)
    if train.all():
        raise LogFormatError(
            f"the log holds one scan of {h} beams x {w} firings: too few to hold out a block of 64 rays; "
            "give a log of two scans or more"
        )
    rng = np.random.default_rng(seed)

    def cap(index, size):
        return np.sort(rng.choice(index, size, replace=False)) if index.size > size else index

    return cap(np.flatnonzero(train), max_train), cap(np.flatnonzero(~train), max_test)


def subsample(index: np.ndarray, size: int, seed: int) -> np.ndarray:
    """At most ``size`` of ``index``, drawn without replacement with ``seed`` and sorted."""
    return np.sort(np.random.default_rng(seed).permutation(index)[:size])


@dataclass
class Splits:
    """The log's rays in the scene, split and traced once (see the module docstring).

    Attributes:
        scene: the loaded scene.
        rays: the log's rays.
        table: the scene's element table.
        train: every training ray (the final joint fit).
        fitting: the training subsample candidates are fitted on.
        test: the held-out rays (every score and test).
        estimation: training rays outside ``fitting`` (learned densities are estimated on them).
        azimuth: (N,) sensor-frame azimuth of every held-out ray, deg.
        n_beams, n_labels: beams of the log and class labels of the scene.
        held_out: the held-out rays described under the given model (:meth:`describe`).
    """

    scene: object
    rays: LogRays
    table: ElementTable
    train: Problem
    fitting: Problem
    test: Problem
    estimation: Problem
    azimuth: np.ndarray
    n_beams: int
    n_labels: int
    held_out: RayTable | None = None
    _states: object = field(default=None, repr=False)

    @classmethod
    def build(cls, log: Log, scene, max_train: int, max_test: int, max_fit: int, seed: int) -> Splits:
        """Split and trace the rays of ``log`` (see :func:`diagnose` for the arguments)."""
        rays = LogRays.from_log(log, scene=scene)
        train_index, test_index = split_rays(log, max_train, max_test, seed)
        fit_index = subsample(train_index, max_fit, seed + 1)
        table = ElementTable.from_scene(scene)
        scan_of = rays.scan[test_index] if log.directions.shape[0] > 1 else np.zeros(test_index.size, int)
        d = log.directions[scan_of, rays.beam[test_index], rays.column[test_index]]
        return cls(
            scene=scene,
            rays=rays,
            table=table,
            train=Problem.build(scene, rays, train_index, table),
            fitting=Problem.build(scene, rays, fit_index, table),
            test=Problem.build(scene, rays, test_index, table),
            estimation=Problem.build(scene, rays, np.setdiff1d(train_index, fit_index), table),
            azimuth=np.degrees(np.arctan2(d[:, 1], d[:, 0])),
            n_beams=log.shape[1],
            n_labels=int(np.asarray(table.label).max()) + 1,
        )

    def whole(self) -> Problem:
        """Every training and held-out ray, traced (the final values are fitted on it once the held-out scores are
        taken: :func:`~mi_lidar.loop.diagnose.diagnose`)."""
        return Problem.build(self.scene, self.rays, np.concatenate([self.train.index, self.test.index]), self.table)

    def describe(self, model: SensorModel) -> RayTable:
        """The held-out rays described under ``model``: first element met, beam, azimuth (:attr:`held_out`)."""
        index = self.test.index
        self.held_out = RayTable(
            ll=np.zeros(index.size),
            measured=self.rays.measured[index],
            hit=self.rays.hit[index],
            sim_range=self.rays.measured[index],
            sim_hit=self.rays.hit[index],
            beam=self.rays.beam[index],
            column=self.rays.column[index],
            scan=self.rays.scan[index],
            azimuth=self.azimuth,
            **first_elements(self.scene, self.table, self.test, model),
        )
        return self.held_out

    def states(self, model: SensorModel):
        """The first element of every estimation ray under ``model`` (traced once; learned densities)."""
        if self._states is None:
            from mi_lidar.loop.sensor_fit import traced_states  # sensor_fit splits its logs with split_rays

            self._states = traced_states(self.estimation, model)
        return self._states

    def realism(self, model: SensorModel, label: str, seed: int, previous: Realism | None = None) -> Realism:
        """Score and sample ``model`` at the held-out rays (:class:`Realism`), warned against ``previous``."""
        index = self.test.index
        ll = self.test.log_likelihood(model)
        sim_range, sim_hit = simulate_log_rays(self.scene, self.table, self.rays, model, seed, index)
        metrics = metrics_of(ll, self.rays.measured[index], self.rays.hit[index], sim_range, sim_hit)
        warning = "" if previous is None else realism_warning(label, previous.metrics, metrics)
        return Realism(label, metrics, warning, ll, sim_range, sim_hit)
