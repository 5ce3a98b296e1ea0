"""evaluate-apps on the Intel log (slow: the planar benchmark fits every simulator, then ~750 application runs)."""

import pytest

from mi_lidar.apps.evaluate import evaluate_log


@pytest.mark.slow
def test_intel_application_risk(shared_data, tmp_path):
    """Measured (8 draws, 1 run): risk registration mi-lidar 0.0139 vs M0 0.0186, M1 0.0143; lines mi-lidar
    0.362 vs M0 0.403, M1 0.403; localization mi-lidar 0.343 vs M0 0.147 (not better: single-run MCL
    divergences dominate it); every simulator's localization pick within 10 % of the best real J."""
    log = shared_data / "carmen" / "intel-corrected.log.gz"
    result = evaluate_log(log, tmp_path, draws=8, runs=1, workers=3)
    risk = {r.name: r.risk for r in result.results}
    assert result.states.n == 182
    assert risk["registration"]["mi-lidar"] < risk["registration"]["M0"] - 0.002, risk
    assert risk["lines"]["mi-lidar"] < min(risk["lines"]["M0"], risk["lines"]["M1"]) - 0.02, risk
    localization = next(r for r in result.results if r.name == "localization")
    assert all(pick["within"] for pick in localization.picks.values()), localization.picks
