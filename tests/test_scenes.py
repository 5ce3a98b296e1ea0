"""Every bundled XML scene loads, renders, and obeys the physics it was built to show."""

import mitsuba as mi
import numpy as np
import pytest
from scipy import stats

import mi_lidar
from mi_lidar.core.channels import tensor_to_numpy

from .conftest import SCENES, rays_along_x

SCENE_FILES = sorted(SCENES.glob("*.xml"))


@pytest.mark.parametrize("path", SCENE_FILES, ids=[p.stem for p in SCENE_FILES])
def test_scene_loads_and_renders(path):
    scene = mi_lidar.load_scene(path)
    channels = tensor_to_numpy(mi.render(scene, seed=0))
    height, width = channels["range"].shape
    sensor = scene.sensors()[0]
    assert (height, width) == sensor.pattern.shape
    hit = channels["hit"]
    assert hit.any()
    assert np.all(np.isfinite(channels["range"][hit])) and np.all(np.isnan(channels["range"][~hit]))
    assert np.all(channels["shape_id"][~hit] == -1) and np.all(channels["shape_id"][hit] >= 0)
    assert np.all((channels["cos_incidence"][hit] >= 0) & (channels["cos_incidence"][hit] <= 1.0001))
    # The fast path traces the same rays and reports the same channels (integer ids, -1 for a miss).
    log = mi_lidar.simulate(scene, seed=0)
    np.testing.assert_array_equal(log.hit[0], hit)
    for name in ("element_id", "shape_id", "label", "segments"):
        assert log.attributes[name].dtype == np.int32
        np.testing.assert_array_equal(log.attributes[name][0], channels[name], err_msg=name)


def test_indoor_wall_range_within_noise():
    # The sensor is at the origin; the east wall's inner face is at x = 5 m; sigma = 0.01 m.
    scene = mi_lidar.load_scene(SCENES / "indoor_planar.xml")
    pattern = scene.sensors()[0].pattern
    forward = int(np.argmax(pattern.directions()[:, 0, 0]))
    ranges = np.array([mi_lidar.simulate(scene, pattern, seed=s).ranges[0, forward, 0] for s in range(40)])
    # Mean of 40 draws: standard error 0.0016 m; allow 4 standard errors plus float32 rounding.
    assert abs(ranges.mean() - 5.0) < 0.007
    assert 0.006 < ranges.std() < 0.014


def test_layer_pass_fraction_is_binomial():
    scene = mi_lidar.load_scene(SCENES / "permeable_layers.xml")
    channels = tensor_to_numpy(mi.render(scene, seed=3))
    n = channels["hit"].size
    passed = np.mean(channels["label"] != 1)
    # Binomial(n, 0.7): 4 standard deviations.
    assert abs(passed - 0.7) < 4 * np.sqrt(0.21 / n)


@pytest.mark.parametrize("probabilities", [(0.3, 0.5, 0.2), (0.6, 0.1, 0.9)])
def test_first_return_frequencies_match_pass_through_law(probabilities):
    scene = mi_lidar.load_scene(
        SCENES / "permeable_layers.xml", p1=probabilities[0], p2=probabilities[1], p3=probabilities[2]
    )
    counts = np.zeros(4)
    for seed in range(4):
        labels = tensor_to_numpy(mi.render(scene, seed=seed))["label"].ravel()
        counts += np.bincount(labels, minlength=5)[1:5]
    p = np.array(probabilities)
    expected = np.array([p[0], (1 - p[0]) * p[1], (1 - p[0]) * (1 - p[1]) * p[2], np.prod(1 - p)])
    chi2 = stats.chisquare(counts, expected * counts.sum())
    assert chi2.pvalue > 1e-3, (counts / counts.sum(), expected)


@pytest.mark.parametrize("max_segments", [1, 2, 3, 4, 5])
def test_beams_stop_after_max_segments_elements(max_segments):
    """Transparent layers (p = 0) at 2, 4 and 6 m before the wall at 8 m: a beam that meets them
    all returns from the wall as its 4th element, or is a miss after ``max_segments`` < 4."""
    import dataclasses

    from mi_lidar.scene.loading import scene_sensor_model

    scene = mi_lidar.load_scene(SCENES / "permeable_layers.xml", p1=0.0, p2=0.0, p3=0.0)
    model = dataclasses.replace(scene_sensor_model(scene)[0], max_segments=max_segments)
    log = mi_lidar.simulate(scene, seed=0, model=model)
    through = log.attributes["segments"] > 0  # beams that meet the layers
    assert through.mean() > 0.9
    assert np.all(log.attributes["segments"][through] == min(max_segments, 4))
    assert np.all(log.hit[through] == (max_segments >= 4))
    if max_segments >= 4:
        assert np.all(log.attributes["label"][through] == 4)
        np.testing.assert_allclose(
            log.attributes["nominal_range"][through], 8.0 / log.directions[0, ..., 0][through[0]], rtol=1e-4
        )


def test_offroad_beams_pass_through_vegetation():
    scene = mi_lidar.load_scene(SCENES / "offroad.xml")
    log = mi_lidar.simulate(scene, seed=0)
    labels, segments, hit = log.attributes["label"], log.attributes["segments"], log.hit
    assert np.any(hit & (labels == 5)) and np.any(hit & (labels == 6))  # shrubs and trees return
    assert np.any(hit & (labels == 1) & (segments > 1))  # ground seen through vegetation


def test_urban_street_labels():
    scene = mi_lidar.load_scene(SCENES / "urban_street.xml")
    labels = tensor_to_numpy(mi.render(scene, seed=0))
    seen = set(np.unique(labels["label"][labels["hit"]]))
    assert {1, 2, 3, 4, 6} <= seen


@pytest.mark.parametrize("rotation", ["", '<rotate z="1" angle="33"/><rotate x="1" angle="7"/>'])
def test_render_and_simulate_agree_ray_for_ray(tmp_path, rotation):
    text = (
        (SCENES / "offroad.xml")
        .read_text()
        .replace('<transform name="to_world"><translate', f'<transform name="to_world">{rotation}<translate')
    )
    path = SCENES / f".rotated_{tmp_path.name}.xml"
    path.write_text(text)
    try:
        scene = mi_lidar.load_scene(path)
    finally:
        path.unlink()
    rendered = tensor_to_numpy(mi.render(scene, seed=11))
    log = mi_lidar.simulate(scene, seed=11)
    np.testing.assert_array_equal(rendered["hit"], log.hit[0])
    np.testing.assert_allclose(rendered["range"], log.ranges[0], rtol=1e-6, equal_nan=True)
    np.testing.assert_array_equal(rendered["element_id"], log.attributes["element_id"][0])


def test_same_seed_identical_different_seeds_independent():
    scene = mi_lidar.load_scene(SCENES / "permeable_layers.xml")
    a, b, c = (tensor_to_numpy(mi.render(scene, seed=s)) for s in (5, 5, 6))
    np.testing.assert_array_equal(a["range"], b["range"])
    same_layer = a["label"] == c["label"]
    # Independent draws agree on the layer with probability sum_k P_k^2 = 0.3^2+0.35^2+0.07^2+0.28^2 = 0.3074.
    assert abs(same_layer.mean() - 0.3074) < 0.02
    noise_a = (a["range"] - a["nominal_range"])[same_layer & (a["label"] == 4)]
    noise_c = (c["range"] - c["nominal_range"])[same_layer & (a["label"] == 4)]
    assert abs(np.corrcoef(noise_a, noise_c)[0, 1]) < 0.05


def test_ellipsoid_returns_match_element_statistics():
    # Rays along +x through the centre of one ellipsoid (sigma_x = 0.5 m at x = 10 m, extent 3):
    # returns follow N(10, 0.5^2) truncated to [8.5, 11.5] (std 0.5 * 0.9866).
    scene = mi.load_dict(
        {
            "type": "scene",
            "veg": {
                "type": "ellipsoids",
                "centers": mi.TensorXf(np.array([[10.0, 0, 0]], np.float32)),
                "scales": mi.TensorXf(np.array([[0.5, 0.3, 0.3]], np.float32)),
                "quaternions": mi.TensorXf(np.array([[0, 0, 0, 1.0]], np.float32)),
            },
        }
    )
    from mi_lidar.core.elements import ElementTable

    n = 100_000
    rays = rays_along_x(n)
    out = mi_lidar.SensorModel().simulate_rays(scene, ElementTable.from_scene(scene), rays, seed=2)
    z = np.asarray(out["range"])
    ref = stats.truncnorm(-3, 3, loc=10.0, scale=0.5)
    assert stats.kstest(z, ref.cdf).statistic < 0.007  # 0.1% KS critical value at n = 1e5 is 0.0062
    assert np.all(np.asarray(out["nominal_range"]) < 8.51)


def test_pattern_table_is_found_next_to_the_scene(tmp_path, monkeypatch):
    from mi_lidar.core.patterns import get_pattern, to_table

    to_table(get_pattern("planar-180"), tmp_path / "beams.npy")
    text = (SCENES / "indoor_planar.xml").read_text().replace('value="planar-360"', 'value="beams.npy"')
    (tmp_path / "room.xml").write_text(text)
    monkeypatch.chdir(SCENES)  # somewhere else than the scene folder
    scene = mi_lidar.load_scene(tmp_path / "room.xml")
    assert tensor_to_numpy(mi.render(scene))["range"].shape == (180, 1)


def test_simulated_ouster_fires_the_real_frame_rays(shared_data):
    from mi_lidar.core.patterns.from_log import pattern_from_log
    from mi_lidar.io import read_any

    real = read_any(shared_data / "ouster" / "OS-1-32-G_v2.1.1_1024x10.pcap")
    log = mi_lidar.simulate(mi_lidar.load_scene(SCENES / "urban_street.xml"), pattern_from_log(real), seed=0)
    assert log.shape == real.shape == (1, 32, 1024)
    np.testing.assert_allclose(log.directions, real.directions, atol=1e-6)
    np.testing.assert_allclose(log.origins, real.origins, atol=1e-7)
    assert 0.3 < log.hit.mean() < 1.0


def test_bundled_scenes_are_found_by_name():
    from mi_lidar.core.errors import SceneError
    from mi_lidar.scene import bundled_scene

    assert bundled_scene("offroad.xml").is_file()
    with pytest.raises(SceneError, match="nowhere.xml: no such bundled scene"):
        bundled_scene("nowhere.xml")


def test_sampling_the_likelihood_trace_gives_the_sampler_scan():
    """The likelihood's tracer (``trace_rounds``) meets the elements the sampler meets, in order, so
    drawing from its trace with the same seed gives the sampler's scan (ranges to float rounding: the
    trace rebuilds surface ranges from the table's triangles), and ``mi.render``, whose last draw is
    fused with the range-image tensor, gives it too."""
    from mi_lidar.core.elements import ElementTable
    from mi_lidar.core.rays import LogRays
    from mi_lidar.core.trace import trace_rounds
    from mi_lidar.scene.loading import scene_sensor_model

    scene = mi_lidar.load_scene(SCENES / "offroad.xml")
    model = scene_sensor_model(scene)[0]
    table = ElementTable.from_scene(scene)
    log = mi_lidar.simulate(scene, seed=4)
    rays, _, _ = LogRays.from_log(log, relative_time=False).batch(np.arange(log.n_rays))
    sampled = model.simulate_rays(scene, table, rays, seed=4)
    assert np.asarray(sampled["segments"]).max() > 1  # beams pass through vegetation
    z, hit = model.sample_trace(table, rays, trace_rounds(scene, table, model, rays), seed=4)
    np.testing.assert_array_equal(np.asarray(hit), np.asarray(sampled["hit"]))
    np.testing.assert_allclose(np.asarray(z), np.asarray(sampled["range"]), atol=1e-4, equal_nan=True)
    rendered = tensor_to_numpy(mi.render(scene, seed=4))
    np.testing.assert_array_equal(rendered["range"].ravel(), np.asarray(sampled["range"]))
