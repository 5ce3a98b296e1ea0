"""NP-Reg's smoothing across states is the thesis's ``H W`` with the Gaussian kernel ``W``.

``kernel_smooth`` applies ``W`` factor by factor (range, then incidence); the test builds ``W``
itself, as the dense (S, S) matrix of the definition, and compares. With beams kept apart, each
beam's counts are then shrunk to its label's (``shrink_beams``).
"""

from __future__ import annotations

import numpy as np
import pytest

from mi_lidar.core.densities.histogram import kernel_smooth, shrink_beams
from mi_lidar.core.densities.tables import PSEUDO_SAMPLES, StateGrid


def dense_kernel(grid: StateGrid, h_range: float, h_incidence: float) -> np.ndarray:
    """``W[s, t] = exp(-dr^2 / 2 h_r^2) exp(-di^2 / 2 h_i^2)`` over the states in ``StateGrid.index_np`` order.

    Beams and labels never mix; the unknown-incidence bin mixes only with itself; the open last range
    bin's centre is 0.5 m past its lower edge.
    """
    edges = np.asarray(grid.range_edges, np.float64)
    upper = np.where(edges[1:] < 1e6, edges[1:], edges[:-1] + 1.0)
    centres_r = 0.5 * (edges[:-1] + upper)
    n_known = len(grid.incidence_edges) - 1 if grid.incidence_edges else 1
    inc_edges = np.asarray(grid.incidence_edges or [0.0, 0.0], np.float64)
    centres_i = 0.5 * (inc_edges[:-1] + inc_edges[1:])

    def parts(state: int) -> tuple[int, int, int]:
        """(beam x label group, incidence bin, range bin) of a flat state index."""
        per_group = grid.n_incidence * grid.n_range
        return state // per_group, (state // grid.n_range) % grid.n_incidence, state % grid.n_range

    w = np.zeros((grid.size, grid.size))
    for s in range(grid.size):
        group_s, i_s, r_s = parts(s)
        for t in range(grid.size):
            group_t, i_t, r_t = parts(t)
            if group_s != group_t:
                continue
            unknown_s, unknown_t = i_s >= n_known, i_t >= n_known
            if unknown_s != unknown_t:
                continue
            di = 0.0 if unknown_s else (centres_i[i_s] - centres_i[i_t]) / h_incidence
            dr = (centres_r[r_s] - centres_r[r_t]) / h_range
            w[s, t] = np.exp(-0.5 * dr**2) * np.exp(-0.5 * di**2)
    return w


@pytest.mark.parametrize(
    "grid",
    [
        StateGrid(
            range_edges=[0.0, 1.0, 2.5, 4.0, 1e9], incidence_edges=[0.0, 30.0, 60.0, 90.0], n_beams=2, n_labels=2
        ),
        StateGrid(range_edges=[0.0, 0.5, 1.0, 1.5, 1e9], n_labels=3),
    ],
    ids=["range-incidence-beams-labels", "range-labels"],
)
def test_kernel_smooth_is_the_dense_kernel_product(grid):
    counts = np.random.default_rng(3).poisson(2.0, (grid.size, 7)).astype(np.float64)
    expected = dense_kernel(grid, 1.3, 25.0) @ counts
    np.testing.assert_allclose(kernel_smooth(grid, counts, 1.3, 25.0), expected, rtol=1e-12, atol=1e-12)


def test_each_beam_is_shrunk_to_its_labels_law_with_the_pseudo_samples_weight():
    """Two labels x three beams x two states, four bins (the last: no returns). Beam 2 of label 1 has no
    data: it gets exactly its label's law with the pseudo samples' weight; a beam with 10,000 samples
    keeps its own law to 0.3 %; pooled beams are left alone."""
    grid = StateGrid(range_edges=[0.0, 5.0, 1e9], n_beams=3, n_labels=2)
    counts = np.zeros((2, 3, 2, 4))
    counts[1, 0] = [[10_000, 0, 0, 0], [0, 5, 5, 0]]
    counts[1, 1] = [[0, 0, 9, 1], [0, 0, 10, 0]]
    counts[0] = np.random.default_rng(5).poisson(3.0, (3, 2, 4))
    shrunk = shrink_beams(grid, counts.reshape(grid.size, 4).copy()).reshape(counts.shape)
    label = counts[1].sum(axis=0)
    np.testing.assert_allclose(shrunk[1, 2], PSEUDO_SAMPLES * label / label.sum(axis=-1, keepdims=True))
    own = shrunk[1, 0, 0] / shrunk[1, 0, 0].sum()
    assert abs(own[0] - 1.0) < 0.003 and np.isclose(shrunk[1, 0, 0].sum(), 10_000 + PSEUDO_SAMPLES)
    # label 0's beams are shrunk to label 0's own sum, not to label 1's
    np.testing.assert_allclose(shrunk[0].sum(axis=(0, -1)), counts[0].sum(axis=(0, -1)) + 3 * PSEUDO_SAMPLES)
    pooled = StateGrid(range_edges=[0.0, 5.0, 1e9], n_labels=2)
    flat = counts.sum(axis=1).reshape(pooled.size, 4)
    assert shrink_beams(pooled, flat) is flat


def test_no_returns_smoothed_with_their_own_range_bandwidth():
    """With ``h_null``, the returns are ``W @ counts`` as before and P(no return) is ``(W' n) / (W' t)``
    with ``W'`` the kernel of range bandwidth ``h_null`` (``n`` the no-returns, ``t`` all outcomes)."""
    grid = StateGrid(range_edges=[0.0, 1.0, 2.5, 4.0, 6.0, 1e9], incidence_edges=[0.0, 30.0, 90.0], n_labels=2)
    counts = np.random.default_rng(4).poisson(3.0, (grid.size, 6)).astype(np.float64)
    smoothed = kernel_smooth(grid, counts, 2.0, 25.0, h_null=0.5)
    np.testing.assert_allclose(smoothed[:, :-1], dense_kernel(grid, 2.0, 25.0) @ counts[:, :-1], rtol=1e-12)
    narrow = dense_kernel(grid, 0.5, 25.0)
    expected = (narrow @ counts[:, -1]) / (narrow @ counts.sum(axis=1))
    np.testing.assert_allclose(smoothed[:, -1] / smoothed.sum(axis=1), expected, rtol=1e-12)
    one_kernel = kernel_smooth(grid, counts, 2.0, 25.0)
    assert not np.allclose(one_kernel[:, -1] / one_kernel.sum(axis=1), expected, rtol=1e-3)
    np.testing.assert_array_equal(kernel_smooth(grid, counts, 2.0, 25.0, h_null=2.0), one_kernel)
