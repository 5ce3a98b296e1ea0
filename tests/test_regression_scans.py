"""The same seed gives the same scans as the stored reference (taken before the wave-2 refactors).

Ranges may differ in the last bits on another CPU (Dr.Jit compiles for the host's vector width and
pass-through restarts accumulate those bits: up to 2.6e-6 relative measured between two EPYC
hosts, 8.1e-6 between an EPYC (AVX2) and a Xeon (AVX-512)), so float channels are compared to
1e-5 m plus 1e-5 relative (0.1 mm at 10 m; any change of the model moves ranges by millimetres or
more); flags, labels and segment counts exactly. The cosine of incidence is compared to 1e-3: on a
curved element it follows the hit point (1e-5 m on a 0.1 m ellipsoid turns the normal by 1e-4
rad), and grazing hits amplify that (3.6e-4 measured between the EPYC and the Xeon); it depends on
the geometry only, which a change of the model leaves alone. A ray that grazes an element's edge
can land on the neighbour on another CPU, so at most one ray in a thousand may differ per channel
(one in 3840 measured; a change of the model moves most rays).
"""

from pathlib import Path

import numpy as np
import pytest

from tests.regression_cases import CASES, simulate_case

MAX_DIFFERING = 1e-3  # fraction of values allowed to differ (edge rays; see the module docstring)
TOLERANCE = {"cos_incidence": (1e-3, 0.0)}  # (absolute, relative) where not 1e-5 m and 1e-5 (module docstring)
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
            atol, rtol = TOLERANCE.get(channel, (1e-5, 1e-5))
            same = np.isclose(value, expected, atol=atol, rtol=rtol, equal_nan=True)
        else:
            same = value == expected
        differing = np.argwhere(~same)
        assert len(differing) <= MAX_DIFFERING * value.size, (
            f"{name}/{channel}: {len(differing)} of {value.size} values differ, first at {differing[:3].tolist()}: "
            f"{value[~same][:3]} instead of {expected[~same][:3]}"
        )
