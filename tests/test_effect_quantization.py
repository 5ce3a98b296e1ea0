"""quantization: ranges on the grid in simulation, step recovered from the likelihood's extra variance."""

import numpy as np
import pytest

from .loop.helpers import hidden_log, recover, room


def test_ranges_lie_on_the_grid():
    scene, model, poses = room(3)
    log, _ = hidden_log(scene, model, poses, "quantization(step=0.05)")
    r = log.ranges[log.hit]
    assert np.allclose(r / 0.05, np.round(r / 0.05), atol=1e-3)


@pytest.mark.slow
def test_recovers_step():
    """A 5 cm step over 1 cm noise comes back within 10 % (variance approximation step^2/12)."""
    scene, model, poses = room(30)
    log, _ = hidden_log(scene, model, poses, "quantization(step=0.05)")
    effect, _ = recover(scene, model, log, "quantization")
    assert abs(float(np.asarray(effect["step"])[0]) - 0.05) < 0.005
