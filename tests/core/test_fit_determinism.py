"""The one fitter gives the same bits in every run: two processes, and two fits in one process, agree exactly.

Dr.Jit differentiates a gather by an atomic scatter-add whose float additions land in a different
order in every run on the LLVM backend's threads, so a density's few parameters read by thousands of
lanes got gradients that differed in their last bits, and Adam carried that into the fitted values (the
beam model: 1 to 4 ulps of float32 on 5,000 synthetic beams, the 4th significant digit on Intel's
131,040 training beams). The fit here is that case: the classic beam model (one state: M1, read per
lane by the density) with a per-beam range bias (read per lane by the effect), on 5,000 synthetic
beams of 8 beam indices.
"""

import json
import subprocess
import sys

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.core.arrays import aligned
from mi_lidar.core.densities import BeamDensity
from mi_lidar.core.effects.range_bias import RangeBias
from mi_lidar.core.elements import ElementTable
from mi_lidar.core.fitting import FitVariable, fixed_point_sums, lookup, natural_gradient
from mi_lidar.core.problem import Problem, fit_parts
from mi_lidar.core.rays import RayBatch
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.core.trace import rounds_from_segments

from ..conftest import REPO

BEAMS = 5000
STEPS = 60


def fitted_bits() -> dict[str, str]:
    """Fit the beam model and a per-beam range bias to synthetic beams; every fitted value as a float32 hex string."""
    rng = np.random.default_rng(1)
    nominal = rng.uniform(0.5, 20.0, BEAMS)
    met = rng.random(BEAMS) > 0.05  # 5 % of the beams meet nothing
    z = nominal + rng.normal(0.0, 0.03, BEAMS) + 0.02 * (np.arange(BEAMS) % 8 == 3)
    short = rng.random(BEAMS) < 0.1
    z[short] *= rng.uniform(0.0, 1.0, short.sum())  # short readings
    hit = (rng.random(BEAMS) > 0.03) & (met | (rng.random(BEAMS) < 0.5))
    start = np.concatenate([[0], np.cumsum(met)])
    table = ElementTable.from_elements(np.ones(int(met.sum())))
    rounds = rounds_from_segments(start, np.arange(int(met.sum())), nominal[met], np.full(int(met.sum()), 0.8))
    rays = RayBatch(
        origin=mi.Point3f(0.0),
        direction=mi.Vector3f(1.0, 0.0, 0.0),
        beam=mi.UInt32(aligned((np.arange(BEAMS) % 8).astype(np.uint32))),
        time=dr.zeros(mi.Float, BEAMS),
        ray_id=dr.arange(mi.UInt32, BEAMS),
    )
    problem = Problem.from_rounds(
        table, rays, rounds, mi.Float(aligned(np.where(hit, z, 0.0).astype(np.float32))), mi.Bool(hit)
    )
    density = BeamDensity(z_max=80.0, escape="shared")
    bias = RangeBias().widen(8, 1)
    model = SensorModel(range_sigma=0.05, max_range=np.inf, max_segments=8, density=density, effects=[bias])
    fit = fit_parts(model, problem, [density, bias], steps=STEPS)
    return {key: np.asarray(value, np.float32).tobytes().hex() for key, value in fit.parameters.items()}


RUN = "import json; from tests.core.test_fit_determinism import fitted_bits; print(json.dumps(fitted_bits()))"


def test_the_same_fit_in_two_processes_gives_the_same_bits():
    runs = [
        subprocess.Popen([sys.executable, "-c", RUN], cwd=REPO, stdout=subprocess.PIPE, text=True) for _ in range(2)
    ]
    first, second = (json.loads(run.communicate()[0]) for run in runs)
    assert all(run.returncode == 0 for run in runs)
    assert set(first) == {"beam.logits", "beam.log_sigma", "beam.log_lambda", "range_bias.bias"}
    assert first == second, [key for key in first if first[key] != second[key]]


def test_the_same_fit_twice_in_one_process_gives_the_same_bits():
    assert fitted_bits() == fitted_bits()


def test_the_fit_still_finds_the_bias_of_the_biased_beam():
    bias = np.frombuffer(bytes.fromhex(fitted_bits()["range_bias.bias"]), np.float32)
    others = np.delete(bias, 3)
    assert bias[3] - np.mean(others) > 0.01  # beam 3 reads 2 cm long


def fixed_point_sum(values: mi.Float, index: mi.UInt32, size: int) -> mi.Float:
    """``out[index[i]] += values[i]`` by :func:`fixed_point_sums` (one group of one part, every lane)."""
    return fixed_point_sums({"": ([(values, index, mi.Bool(True))], size)})[""]


def test_fixed_point_sums_match_float64_sums_in_any_lane_order():
    rng = np.random.default_rng(2)
    values = (rng.standard_normal(100_000) * np.exp(rng.uniform(-20.0, 5.0, 100_000))).astype(np.float32)
    index = rng.integers(0, 5, 100_000)
    exact = np.bincount(index, weights=values.astype(np.float64), minlength=5)
    sums = []
    for order in (np.arange(index.size), rng.permutation(index.size)):
        total = fixed_point_sum(mi.Float(values[order]), mi.UInt32(index[order].astype(np.uint32)), 5)
        sums.append(np.asarray(total))
    assert sums[0].tobytes() == sums[1].tobytes()
    np.testing.assert_allclose(sums[0], exact, rtol=2e-7, atol=1e-9 * np.abs(values).max())


def test_a_non_finite_lane_makes_the_sums_nan():
    total = fixed_point_sum(mi.Float([1.0, np.inf, 2.0]), mi.UInt32([0, 1, 0]), 2)
    assert np.all(np.isnan(np.asarray(total)))


def test_lookup_gradients_in_a_fit_equal_dr_jit_gather_gradients():
    """The fitter's gradient of a loss read through lookups and directly equals Dr.Jit's own (plain gathers)."""
    rng = np.random.default_rng(3)
    index = mi.UInt32(rng.integers(0, 3, 10_000).astype(np.uint32))
    x = mi.Float(rng.standard_normal(10_000).astype(np.float32))
    start = np.array([0.2, -0.1, 0.4])

    def loss_of(w, read):
        return dr.mean(dr.square(read(w, index) - x)) + dr.sum(dr.square(w))

    def objective(values, step):
        loss = loss_of(values()["w"], lookup)
        dr.backward(loss)
        return float(loss[0])

    total, gradient = natural_gradient([FitVariable("w", start, scale=1.0, transform="value")], objective)
    w = mi.Float(start.astype(np.float32))
    dr.enable_grad(w)
    loss = loss_of(w, lambda values, i: dr.gather(mi.Float, values, i))
    dr.backward(loss)
    assert total == float(loss[0])
    np.testing.assert_allclose(np.asarray(gradient["w"]), np.asarray(dr.grad(w)), rtol=1e-5)


def test_lookups_of_arrays_computed_from_the_values_carry_back_exactly():
    """Lookups of arrays computed from the fitted values (as ``calibrate`` scatters fitted elements into a
    scene's per-element table, and builds the table anew per chunk) get Dr.Jit's own gradient, with the same
    bits in a second call."""
    rng = np.random.default_rng(4)
    index = mi.UInt32(rng.integers(0, 6, 20_000).astype(np.uint32))
    x = mi.Float(rng.standard_normal(20_000).astype(np.float32))
    start = np.array([0.3, -0.2, 0.5])
    slots = mi.UInt32([1, 3, 4])

    def loss_of(w, read):
        total = dr.sum(dr.square(w))
        for chunk in range(2):  # one table per chunk, both from the same values
            table = dr.full(mi.Float, 0.25, 6)
            dr.scatter(table, dr.exp(w) + chunk, slots)
            total += dr.mean(dr.square(read(table, index) - x)) + dr.mean(read(table, index) * x)
        return total

    def objective(values, step):
        loss = loss_of(values()["w"], lookup)
        dr.backward(loss)
        return float(loss[0])

    runs = [natural_gradient([FitVariable("w", start, scale=1.0, transform="value")], objective) for _ in range(2)]
    w = mi.Float(start.astype(np.float32))
    dr.enable_grad(w)
    loss = loss_of(w, lambda values, i: dr.gather(mi.Float, values, i))
    dr.backward(loss)
    assert runs[0][0] == float(loss[0])
    np.testing.assert_allclose(np.asarray(runs[0][1]["w"]), np.asarray(dr.grad(w)), rtol=1e-5)
    assert np.asarray(runs[0][1]["w"]).tobytes() == np.asarray(runs[1][1]["w"]).tobytes()
