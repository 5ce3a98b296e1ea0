"""Scan-regression cases: fixed scenes, patterns, poses, effects and seeds whose scans must not change.

Each case simulates a few small scans of a bundled scene with :func:`mi_lidar.simulate` and returns
the channels that do not depend on the order in which Mitsuba loads shapes (range, hit, label,
incidence, nominal range, segments). ``tools/make_regression_scans.py`` stores them in
``tests/data/regression_scans.npz``; ``tests/test_regression_scans.py`` compares.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

SCENES = Path(__file__).resolve().parents[1] / "scenes_xml"
CHANNELS = ("range", "hit", "label", "cos_incidence", "nominal_range", "segments")


def _poses(n: int, step: float, height: float) -> np.ndarray:
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = np.arange(n) * step
    poses[:, 2, 3] = height
    return poses


# name -> (scene file, pattern name, pattern options, poses, effects spec, seed). Dropouts stop the beam by
# default since wave 2; `mode=pass` asks for the behaviour the reference was taken with.
CASES = {
    "indoor_planar": ("indoor_planar.xml", "planar-360", {}, None, "", 3),
    "permeable_layers": ("permeable_layers.xml", None, {}, None, "", 1),
    "offroad": ("offroad.xml", "vlp16", {"n_firings": 90}, _poses(2, 1.5, 1.8), "", 0),
    "urban_effects": (
        "urban_street.xml",
        "hdl32e",
        {"n_firings": 60},
        _poses(2, 2.0, 1.8),
        "range_noise(law=physics, sigma0=0.01, k=1e-4), outliers(p_near=0.02, p_uniform=0.01), "
        "incidence_dropout(gamma=1.5, mode=pass), range_bias(bias=0.02)",
        5,
    ),
    "urban_footprint": (
        "urban_street.xml",
        "vlp16",
        {"n_firings": 45},
        _poses(1, 0.0, 1.8),
        "mixed_pixels(divergence=0.004)",
        7,
    ),
}


def simulate_case(name: str) -> dict[str, np.ndarray]:
    """Simulate case ``name``; channels of :data:`CHANNELS` as (S, H, W) arrays."""
    import dataclasses

    import mi_lidar
    from mi_lidar.core.effects import parse_effects
    from mi_lidar.core.patterns import get_pattern
    from mi_lidar.scene.loading import scene_sensor_model

    scene_file, pattern, options, poses, effects, seed = CASES[name]
    scene = mi_lidar.load_scene(SCENES / scene_file)
    model = scene_sensor_model(scene)[0]
    if effects:
        model = dataclasses.replace(model, effects=parse_effects(effects))
    log = mi_lidar.simulate(
        scene, get_pattern(pattern, **options) if pattern else None, poses=poses, seed=seed, model=model
    )
    out = {"range": log.ranges, "hit": log.hit}
    out.update({k: log.attributes[k] for k in CHANNELS if k in log.attributes})
    return out
