"""The same seed gives the same scans as the stored reference (taken before the wave-2 refactors).

Ranges may differ in the last bits on another CPU (Dr.Jit compiles for the host's vector width), so
float channels are compared to 1e-5 m / 1e-5; flags, labels and segment counts exactly.
"""

from pathlib import Path

import numpy as np
import pytest

from tests.regression_cases import CASES, simulate_case

REFERENCE = Path(__file__).resolve().parent / "data" / "regression_scans.npz"


@pytest.mark.parametrize("name", sorted(CASES))
def test_scans_match_the_stored_reference(name):
    reference = np.load(REFERENCE)
    got = simulate_case(name)
    stored = {key.split("/", 1)[1]: reference[key] for key in reference.files if key.startswith(name + "/")}
    assert set(got) == set(stored)
    for channel, expected in stored.items():
        value = got[channel]
        assert value.shape == expected.shape, channel
        if value.dtype.kind == "f":
            np.testing.assert_allclose(value, expected, atol=1e-5, rtol=0, equal_nan=True, err_msg=channel)
        else:
            np.testing.assert_array_equal(value, expected, err_msg=channel)
