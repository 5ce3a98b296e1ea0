"""How much neighbouring beams of a real scan share their errors, measured against a model's own samples.

A model's beams are scored one by one, so the likelihood cannot see whether the errors of
neighbouring beams are shared; applications that fit lines or match scans do. The measure is the
probability integral transform (PIT) of every measured beam under the model's law at that beam,
estimated from ``references`` independent samples (:func:`pit_scores`): if the model's law is right,
a beam's PIT is uniform; if neighbouring beams' errors are shared, their PITs, mapped to normal
scores, correlate (:func:`lag_correlations`). A scan sampled with independent beams shows none.

:func:`fit_beam_correlation` chooses the :class:`~mi_lidar.core.streams.BeamCorrelation` of the
sampler's streams so that sampled scans show the real scans' correlations at lags 1, 2, 3, 5 and 10
beams, measured the same way against the same references: the least sum of squared differences over a
grid of shared shares ``w`` and decays ``rho`` (the sampler's transforms weaken a latent correlation,
so the latent one is chosen by what the samples show, not set to the measured one). Every candidate
draws its scans with the same seed, so the choice does not jump with sampling noise. The choice uses
the training scans only.
"""

from __future__ import annotations

import numpy as np
from scipy.special import ndtri

from mi_lidar.core.streams import BeamCorrelation

LAGS = (1, 2, 3, 5, 10)  # lags (beams) the sampled and real correlations are matched at
SHARED_GRID = (0.0, 0.3, 0.5, 0.7, 0.8, 0.9, 0.95, 0.97, 0.99, 0.999)  # candidate shared shares w
RHO_GRID = (0.5, 0.7, 0.8, 0.9, 0.95, 0.97, 0.98, 0.99, 0.995)  # candidate decays rho


def pit_scores(
    z: np.ndarray, hit: np.ndarray, ref_z: np.ndarray, ref_hit: np.ndarray, rng: np.random.Generator
) -> np.ndarray:
    """(B,) normal scores of the randomized PIT of measurements under reference samples.

    Args:
        z, hit: (B,) measured range (m) and return flag.
        ref_z, ref_hit: (M, B) independent samples of the model at the same beams.
        rng: draws the randomization of ties (a miss ties with every sampled miss).

    Returns:
        ``Phi^-1((L + V (E + 1)) / (M + 1))`` with ``L`` the references below the measurement (a miss
        lies above every range), ``E`` the ties and ``V`` uniform: standard normal for a measurement
        exchangeable with the references.
    """
    value = np.where(hit, np.nan_to_num(z, nan=np.inf), np.inf)
    ref = np.where(ref_hit, np.nan_to_num(ref_z, nan=np.inf), np.inf)
    below = np.sum(ref < value, axis=0)
    ties = np.sum(ref == value, axis=0)
    u = (below + rng.random(value.size) * (ties + 1)) / (ref.shape[0] + 1)
    return ndtri(u)


def lag_correlations(scores: np.ndarray, scan: np.ndarray, beam: np.ndarray, lags=LAGS) -> np.ndarray:
    """(len(lags),) correlation of the scores of beams ``k`` apart in one scan, for each lag ``k``.

    Pairs are found by (scan, beam), so any order of the beams works; NaN where no pair exists.
    """
    key = np.asarray(scan, np.int64) * (int(np.max(beam)) + 1 + max(lags)) + np.asarray(beam, np.int64)
    order = np.argsort(key)
    sorted_key = key[order]
    out = []
    for k in lags:
        at = np.searchsorted(sorted_key, key + k)
        found = (at < key.size) & (sorted_key[np.minimum(at, key.size - 1)] == key + k)
        a, b = scores[found], scores[order[at[found]]]
        out.append(float(np.corrcoef(a, b)[0, 1]) if a.size > 2 else float("nan"))
    return np.array(out)


def fit_beam_correlation(sample, z, hit, scan, beam, references: int = 16, seed: int = 0):
    """The :class:`~mi_lidar.core.streams.BeamCorrelation` whose sampled scans share errors as the real ones do.

    Args:
        sample: ``sample(correlation, seed) -> (z, hit)``: one sampled scan set of the beams (m; a
            miss has ``hit`` False).
        z, hit, scan, beam: (B,) the measured beams and their indices.
        references: independent samples the PIT is measured against.
        seed: seed of the references (the candidates' scans use the next seed).

    Returns:
        The correlation, and a summary ``{"lags", "real", "sampled", "uncorrelated"}``: the lags and
        the lag correlations of the real scans, of scans sampled with the chosen correlation and of
        scans sampled with independent beams.
    """
    draws = [sample(BeamCorrelation(), seed + k) for k in range(references)]
    ref_z, ref_hit = np.stack([d[0] for d in draws]), np.stack([d[1] for d in draws])

    def lags_of(z_, hit_) -> np.ndarray:
        scores = pit_scores(z_, hit_, ref_z, ref_hit, np.random.default_rng(seed))
        return lag_correlations(scores, scan, beam, LAGS)

    real = lags_of(z, hit)
    probe = seed + references
    candidates = [BeamCorrelation()] + [BeamCorrelation(w, rho) for w in SHARED_GRID[1:] for rho in RHO_GRID]
    sampled = [lags_of(*sample(c, probe)) for c in candidates]
    misfit = [float(np.nansum((s - real) ** 2)) for s in sampled]
    best = int(np.argmin(misfit))
    summary = {"lags": list(LAGS), "real": real, "sampled": sampled[best], "uncorrelated": sampled[0]}
    return candidates[best], summary
