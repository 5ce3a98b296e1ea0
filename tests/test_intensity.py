"""Reflectivity and returned intensity: sources of reflectivity, the intensity laws, sampling against the
likelihood, gradients against finite differences, weak-return dropout, and intensity through every writer."""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_lidar
from mi_lidar.calibration.intensity import calibrate_intensity, fit_intensity
from mi_lidar.core.effects import make_effect, parse_effects
from mi_lidar.core.elements import ElementTable
from mi_lidar.core.errors import LogFormatError, ParameterError, SceneError
from mi_lidar.core.intensity import IntensityModel, parse_intensity
from mi_lidar.core.patterns import get_pattern
from mi_lidar.core.problem import Problem
from mi_lidar.core.rays import LogRays, RayBatch
from mi_lidar.core.segment import Segment
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.io import read_any, write_any
from mi_lidar.scene.dicts import EllipsoidElements, MeshElements, save_scene, scene_dict

from .reflective_world import mitsuba_scene, poses, rectangles


def segment(nominal, cos, rho) -> Segment:
    n = len(nominal)
    zero = dr.zeros(mi.Float, n)
    return Segment(
        valid=dr.full(mi.Bool, True, n),
        nominal=mi.Float(nominal),
        p=zero + 1,
        mean=mi.Float(nominal),
        sigma=zero + 0.01,
        lo=zero - dr.inf,
        hi=zero + dr.inf,
        cos_incidence=mi.Float(cos),
        element=dr.zeros(mi.UInt32, n),
        shape=dr.zeros(mi.UInt32, n),
        label=dr.zeros(mi.UInt32, n),
        kind=dr.zeros(mi.UInt32, n),
        reflectivity=mi.Float(rho),
    )


def rays_of(beams) -> RayBatch:
    n = len(beams)
    return RayBatch(
        origin=mi.Point3f(0, 0, 0),
        direction=mi.Vector3f(1, 0, 0),
        beam=mi.UInt32(beams),
        time=dr.zeros(mi.Float, n),
        ray_id=dr.arange(mi.UInt32, n),
    )


def test_reflectivity_from_material_face_property_and_ellipsoid_attribute(tmp_path):
    """lidar_material's reflectivity (default: its camera reflectance), PLY face values and ellipsoid
    attributes reach the element table, in that order of precedence."""
    scene = mi.load_dict(
        {
            "type": "scene",
            "a": {"type": "rectangle", "bsdf": {"type": "lidar_material", "reflectivity": 0.07}},
            "b": {"type": "sphere", "bsdf": {"type": "lidar_material", "reflectance": 0.3}},
        }
    )
    assert np.allclose(np.asarray(ElementTable.from_scene(scene).reflectivity)[:3], [0.07, 0.07, 0.3], atol=1e-6)
    mesh = MeshElements(
        np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float),
        np.array([[0, 1, 2], [1, 3, 2]]),
        p_hit=np.ones(2),
        label=np.zeros(2),
        reflectivity=np.array([0.2, 1.7]),
    )
    blobs = EllipsoidElements(
        np.zeros((2, 3)),
        np.ones((2, 3)),
        np.tile([0, 0, 0, 1.0], (2, 1)),
        np.ones(2),
        np.zeros(2),
        3.0,
        np.array([0.4, 5.0]),
    )
    path = save_scene(tmp_path / "s.xml", {"m": mesh, "e": blobs})
    for loaded in (mi_lidar.load_scene(path), mi.load_dict(scene_dict({"m": mesh, "e": blobs}))):
        assert sorted(np.round(np.asarray(ElementTable.from_scene(loaded).reflectivity), 5)) == [0.2, 0.4, 1.7, 5.0]


def test_bad_reflectivity_is_rejected():
    with pytest.raises((ParameterError, RuntimeError), match="reflectivity=-0.1"):
        mi.load_dict({"type": "lidar_material", "reflectivity": -0.1})
    mesh = MeshElements(np.eye(3), np.array([[0, 1, 2]]), np.ones(1), np.zeros(1), reflectivity=np.array([np.nan]))
    with pytest.raises((SceneError, ParameterError, RuntimeError), match="reflectivity"):
        ElementTable.from_scene(mi.load_dict(scene_dict({"m": mesh})))


def test_intensity_laws():
    """reflectivity law: gain rho cos o(r); signal law: times (10 m / r)^n; per-beam gains."""
    seg = segment([5.0, 20.0, 0.5], [1.0, 0.5, 1.0], [0.4, 0.8, 1.0])
    model = IntensityModel(gain=[100.0, 200.0], near_range=0.5)
    overlap = 1 - np.exp(-((np.array([5.0, 20.0, 0.5]) / 0.5) ** 2))
    expect = np.array([100 * 0.4, 200 * 0.8 * 0.5, 200 * 1.0]) * overlap
    assert np.allclose(np.asarray(model.expected(seg, rays_of([0, 1, 5]))), expect, rtol=1e-5)
    signal = IntensityModel(law="signal", gain=1000.0, range_exponent=2.0, incidence_exponent=2.0, near_range=0.0)
    values = np.asarray(signal.expected(seg, rays_of([0, 0, 0])))
    assert np.allclose(values, 1000 * np.array([0.4 * 4, 0.8 * 0.25 * 0.25, 1.0 * 400]), rtol=1e-5)
    rho = signal.apparent_reflectivity(values, [5.0, 20.0, 0.5], [1.0, 0.5, 1.0], [0, 0, 0])
    assert np.allclose(rho, [0.4, 0.8, 1.0], rtol=1e-5)  # the law inverted


def test_samples_follow_the_scored_density():
    """Sampled intensities (seeded, 20000 lanes) have the mean and spread of the scored Gaussian within 1 %
    and 3 %, and are integers clipped to [0, max_value]."""
    n = 20000
    seg = segment(np.full(n, 8.0), np.full(n, 0.8), np.full(n, 0.5))
    model = IntensityModel(gain=100.0, noise_floor=2.0, noise_relative=0.1, max_value=255.0, p_outlier=0.0)
    u = mi.Float(np.random.default_rng(0).uniform(size=n).astype(np.float32))
    draws = np.asarray(model.sample(seg, u, rays_of(np.zeros(n, np.uint32))))
    mean = float(np.asarray(model.expected(seg, rays_of([0])))[0])
    assert np.all(draws == np.round(draws)) and draws.min() >= 0 and draws.max() <= 255
    assert draws.mean() == pytest.approx(mean, rel=0.01)
    assert draws.std() == pytest.approx(float(np.asarray(model.sigma(mi.Float(mean)))[0]), rel=0.03)
    grid = np.arange(0, 80, dtype=np.float32)
    density = np.exp(
        np.asarray(
            model.log_prob(
                segment(np.full(80, 8.0), np.full(80, 0.8), np.full(80, 0.5)),
                mi.Float(grid),
                rays_of(np.zeros(80, np.uint32)),
            )
        )
    )
    assert density.sum() == pytest.approx(1.0, abs=0.01)


def street_log(model, n_firings=60):
    scene = mi_lidar.load_scene(mi_lidar.__path__[0] + "/../scenes_xml/urban_street.xml")
    pose = mi_lidar.scene.scene_sensor_model(scene)[1]
    return scene, mi_lidar.simulate(
        scene, get_pattern("vlp16", n_firings=n_firings), poses=pose[None], model=model, seed=2
    )


def test_simulated_intensity_and_joint_likelihood():
    """Simulated returns carry intensities (0 for misses); scoring them adds a finite, negative term to the
    mean log-likelihood; a log without the attribute is refused with a message naming it."""
    model = SensorModel(intensity=IntensityModel(gain=120.0))
    scene, log = street_log(model)
    intensity = log.attributes["intensity"]
    assert np.all(intensity[~log.hit] == 0) and intensity[log.hit].mean() > 5
    ranges_only = Problem.build(scene, LogRays.from_log(log)).nll(model)
    joint = Problem.build(scene, LogRays.from_log(log, intensity="intensity")).nll(model)
    assert np.isfinite(joint) and joint > ranges_only + 1.0
    with pytest.raises(LogFormatError, match="signal"):
        LogRays.from_log(log, intensity="signal")


def test_joint_likelihood_gradients_match_finite_differences():
    """d(sum ll)/d(gain) and d(sum ll)/d(reflectivity of one element) agree with central differences to 2 %."""
    model = SensorModel(intensity=IntensityModel(gain=120.0))
    scene, log = street_log(model, n_firings=30)
    problem = Problem.build(scene, LogRays.from_log(log, intensity="intensity"))
    trial = SensorModel(intensity=IntensityModel(gain=100.0))
    problem.trace(trial)
    chunk = problem.chunks[0]
    element = int(np.bincount(log.attributes["element_id"][log.hit]).argmax())
    base = np.asarray(problem.table.reflectivity).copy()

    def total(gain, rho, grad=False):
        trial.intensity.params["gain"] = mi.Float(gain)
        values = base.copy()
        values[element] = rho
        problem.table = problem.table.replaced(reflectivity=mi.Float(values))
        if grad:
            dr.enable_grad(trial.intensity.params["gain"], problem.table.reflectivity)
        ll = dr.sum(problem.chunk_log_likelihood(trial, chunk))
        if not grad:
            return float(ll[0])
        dr.backward(ll)
        return float(dr.grad(trial.intensity.params["gain"])[0]), float(dr.grad(problem.table.reflectivity)[element])

    rho = float(base[element])
    auto_gain, auto_rho = total(100.0, rho, grad=True)
    numeric_gain = (total(100.5, rho) - total(99.5, rho)) / 1.0
    numeric_rho = (total(100.0, rho + 0.005) - total(100.0, rho - 0.005)) / 0.01
    assert auto_gain == pytest.approx(numeric_gain, rel=0.02)
    assert auto_rho == pytest.approx(numeric_rho, rel=0.02)


def test_calibrated_reflectivities_shrink_by_a_held_out_width():
    """Reflective world (seeded), starting reflectivities off by a factor exp(N(0, 0.5)): the calibrated
    expected intensity of the faces met by 30+ fit rays is within 5 % of the truth (median 1 %; the start:
    above 25 %), the relative noise is the true 0.1 (measured 0.102), the width is chosen on the check columns
    (0 keeps the start and scores worse there), and a prior of width 0 leaves the reflectivities alone."""
    scene = mitsuba_scene(rectangles())
    truth = SensorModel(intensity=IntensityModel(gain=120.0, noise_floor=1.0, noise_relative=0.1, p_outlier=0.0))
    log = mi_lidar.simulate(scene, get_pattern("vlp16", n_firings=90), poses=poses(4), model=truth, seed=1)
    table = ElementTable.from_scene(scene)
    rho_true = np.asarray(table.reflectivity, np.float64)
    start = rho_true * np.exp(np.random.default_rng(3).normal(0.0, 0.5, rho_true.size))
    table = table.replaced(reflectivity=mi.Float(start.astype(np.float32)))
    rays = LogRays.from_log(log, intensity="intensity")
    fit, check = np.flatnonzero(rays.column % 2 == 0), np.flatnonzero(rays.column % 2 == 1)
    model = SensorModel(intensity=IntensityModel(gain=100.0))
    result = calibrate_intensity(model, scene, table, rays, fit, check, steps=60, sigmas=(0.0, 0.3, np.inf))
    assert result.prior_sigma > 0 and result.selection[0.0] > result.selection[result.prior_sigma] + 0.05
    gain = float(np.asarray(model.intensity["gain"])[0])
    met = np.bincount(log.attributes["element_id"].ravel()[fit][rays.hit[fit]], minlength=rho_true.size) >= 30
    error = np.abs(np.log(gain * result.reflectivity / (120.0 * rho_true)))[met]
    assert met.sum() >= 8 and np.median(error) < 0.05
    assert np.median(np.abs(np.log(gain * start / (120.0 * rho_true)))[met]) > 0.25
    relative = float(np.asarray(model.intensity["noise_relative"])[0])
    assert 0.08 < relative < 0.13  # the true 0.1: neither collapsed nor inflated by the starting errors (0.38)
    kept = Problem.build(scene, rays, fit, table)
    fit_intensity(model, kept, steps=5, prior_sigma=0.0)
    assert np.array_equal(np.asarray(kept.table.reflectivity), np.asarray(table.reflectivity))


def test_intensity_fits_refuse_bad_input():
    """Rays without intensities, a negative prior width and a log of several scans are refused by name."""
    from mi_lidar.core.errors import CalibrationError
    from mi_lidar.loop.real_intensity import intensity_experiment

    model = SensorModel(intensity=IntensityModel(gain=120.0))
    scene, log = street_log(model, n_firings=10)
    with pytest.raises(CalibrationError, match="intensity="):
        fit_intensity(model, Problem.build(scene, LogRays.from_log(log)))
    with pytest.raises(CalibrationError, match="prior_sigma=-1"):
        fit_intensity(model, Problem.build(scene, LogRays.from_log(log, intensity="intensity")), prior_sigma=-1.0)
    with pytest.raises(LogFormatError, match="2 scans"):
        intensity_experiment(log.select([0, 0]), "intensity")


def test_reflectivity_dropout_keep_law():
    """keep = logistic((ln(rho cos) - 2 ln(r / range50)) / width): half at range50 sqrt(rho cos)."""
    effect = make_effect("reflectivity_dropout", range50=60.0, width=0.5)
    r = np.array([60 * np.sqrt(0.1), 11.5, 31.3, 60.0])
    keep = np.asarray(effect.keep(segment(r, [1.0, 1.0, 1.0, 0.5], [0.1, 0.1, 0.1, 1.0]), rays_of([0, 0, 0, 0])))
    margin = (np.log(np.array([0.1, 0.1, 0.1, 0.5])) - 2 * np.log(r / 60)) / 0.5
    assert np.allclose(keep, 1 / (1 + np.exp(-margin)), atol=1e-5)
    assert keep[0] == pytest.approx(0.5, abs=1e-4) and keep[1] == pytest.approx(0.88, abs=0.01)


def test_sampled_dropout_follows_the_keep_law():
    """In the reflective world (seeded), the share of first elements that return, per reflectivity, matches
    the mean keep probability of the law within 3 binomial sigmas (+ 0.01)."""
    scene = mitsuba_scene(rectangles())
    model = SensorModel(effects=parse_effects("reflectivity_dropout(range50=40, width=0.4)"))
    clean = mi_lidar.simulate(scene, get_pattern("vlp16", n_firings=90), poses=poses(6), model=SensorModel(), seed=0)
    log = mi_lidar.simulate(scene, get_pattern("vlp16", n_firings=90), poses=poses(6), model=model, seed=0)
    rho = np.asarray(ElementTable.from_scene(scene).reflectivity)[np.maximum(clean.attributes["element_id"], 0)]
    power = rho * clean.attributes["cos_incidence"]
    with np.errstate(divide="ignore", invalid="ignore"):  # misses: no power
        keep = 1 / (1 + np.exp(-(np.log(power) - 2 * np.log(clean.attributes["nominal_range"] / 40)) / 0.4))
    for value in (0.04, 0.12, 0.9):
        met = clean.hit & np.isclose(rho, value)
        expect = keep[met].mean()
        tolerance = 3 * np.sqrt(expect * (1 - expect) / met.sum()) + 0.01
        assert abs(log.hit[met].mean() - expect) < tolerance, (value, log.hit[met].mean(), expect)


def test_parse_intensity():
    assert parse_intensity("").choices["law"] == "reflectivity"
    assert parse_intensity("intensity(law=signal, gain=900)").choices["law"] == "signal"
    with pytest.raises(ParameterError, match="intensity"):
        parse_intensity("loudness(gain=1)")


@pytest.mark.parametrize("suffix", [".npz", ".exr", ".ply", ".pcd", ".bin", ".las", "rosbag2"])
def test_intensity_survives_every_writer(tmp_path, suffix):
    """A simulated scan's intensities come back from every writer (exactly; LAS and KITTI as float32)."""
    _, log = street_log(SensorModel(intensity=IntensityModel(law="signal", gain=900.0, max_value=65535.0)))
    path = tmp_path / ("scan" + suffix if suffix != "rosbag2" else "bag")
    write_any(log, path, fmt="rosbag2" if suffix == "rosbag2" else None, scan=0)
    back = read_any(path)
    written = log.attributes["intensity"][log.hit]
    assert written.max() > 100
    source = back.attributes["intensity"] if "intensity" in back.attributes else back.attributes["attr.intensity"]
    if back.shape == log.shape:
        assert np.array_equal(source[back.hit], written)
    else:
        assert np.array_equal(np.sort(source[back.hit].ravel()), np.sort(written))
