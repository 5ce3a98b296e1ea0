"""Geometry fits reuse their compiled kernels from step to step.

Fitting geometry re-traces every mini-batch, so the rounds of the trace records change length at
every step. A length written into a kernel as a constant makes Dr.Jit compile that kernel again
for every batch (about 1 s per step on 2 cores); the kernels must instead be found in Dr.Jit's
in-memory cache after the first steps. Checked with Dr.Jit's kernel history, never with times.

A round that holds a single ray compiles kernels of its own (Dr.Jit specializes width-1 arrays),
once per round depth; the model here stops at 4 elements per ray, so that no round of a
4096-ray batch is that short and the check is exact.
"""

import drjit as dr
import numpy as np

import mi_lidar
from mi_lidar.calibration.fit import Calibration, FitOptions
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.scene.dicts import scene_dict

from .scenes import bowl, bushes, pattern, sensor_pose

MODEL = SensorModel(range_sigma=0.02, max_segments=4)  # every round of a batch keeps hundreds of rays
WARM_UP = 2  # steps that may launch new kernels (the first trace, Adam's first two updates)
CHECKED = 5  # steps after the warm-up that must launch none (the last step, with its held-out evaluation, follows)


def new_kernels_per_step(names: list[str], steps: int) -> list[int]:
    """Kernels launched in each Adam step of a fit of ``names`` that no earlier step launched.

    The scene is the bowl with 24 permeable ellipsoids in front of it (rays meet up to several
    elements, so the trace has several rounds); the fit starts from the truth with ellipsoid scales
    enlarged by 10 % and draws a new mini-batch of 4096 rays at every step.
    """
    truth = bushes()
    log = mi_lidar.simulate(
        mi_lidar.load_scene(scene_dict({"terrain": bowl(n=9), "bushes": truth})),
        pattern(250),
        poses=np.stack([sensor_pose(), sensor_pose(0.4, 0.0, 1.0)]),
        seed=5,
        model=MODEL,
    )
    start = bushes()
    start.scales = start.scales * 1.1
    cal = Calibration(
        mi_lidar.load_scene(scene_dict({"terrain": bowl(n=9), "bushes": start})),
        log,
        names,
        model=MODEL,
        options=FitOptions(steps=steps, batch_size=1 << 12, eval_every=steps + 1, counting_start=False, seed=1),
    )
    seen, counts = set(), []

    def progress(step, total, train_loss, held_out_loss):
        launched = {k["hash"] for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT}
        counts.append(len(launched - seen))
        seen.update(launched)

    enabled = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        cal.fit(progress)
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, enabled)
    return counts


def test_ellipsoid_scale_steps_reuse_kernels():
    counts = new_kernels_per_step(["elements.bushes.scales"], steps=WARM_UP + CHECKED + 1)
    assert counts[WARM_UP:-1] == [0] * CHECKED, f"new kernels per step: {counts}"


def test_terrain_height_steps_reuse_kernels():
    counts = new_kernels_per_step(["terrain.terrain.heights"], steps=WARM_UP + CHECKED + 1)
    assert counts[WARM_UP:-1] == [0] * CHECKED, f"new kernels per step: {counts}"
