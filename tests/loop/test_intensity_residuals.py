"""compare and diagnose show intensity residuals beside the range residuals whenever the log carries intensities."""

import numpy as np

from mi_lidar.core.intensity import IntensityModel
from mi_lidar.core.patterns import get_pattern
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.loop import compare, diagnose
from mi_lidar.loop.intensity_residuals import IntensityResiduals
from mi_lidar.scene.simulation import simulate

from .helpers import street


def street_log(n_firings: int = 180):
    """The street scene (VLP-16) and one seeded scan whose intensities fall off as cos(incidence)."""
    scene, _, poses = street(1)
    truth = SensorModel(intensity=IntensityModel(gain=120.0, incidence_exponent=1.0))
    return scene, simulate(scene, get_pattern("vlp16", n_firings=n_firings), poses=poses, model=truth, seed=2)


def ratio_by_incidence(result) -> dict:
    return {row["group"]: row["intensity_ratio"] for row in result.intensity.breakdown("incidence")}


def test_compare_reports_intensity_residuals_by_incidence(tmp_path):
    """A model without the incidence falloff is off by the cosine: its measured / model ratio falls from above
    0.9 head-on to below 0.4 at 75-90 deg; the true model's stays within 10 % of 1 in every incidence group
    (seeded). The report carries the section and its figure; a log without intensities has neither."""
    scene, log = street_log()
    flat = SensorModel(intensity=IntensityModel(gain=120.0, incidence_exponent=0.0))
    result = compare(log, scene, flat, out=tmp_path / "flat")
    ratio = ratio_by_incidence(result)
    assert ratio["00-15 deg"] > 0.9 and ratio["75-90 deg"] < 0.4, ratio
    true = ratio_by_incidence(compare(log, scene, SensorModel(intensity=IntensityModel(gain=120.0))))
    assert all(abs(value - 1.0) < 0.1 for value in true.values()), true
    report = (tmp_path / "flat" / "report.md").read_text()
    assert log.n_rays >= 1000 and f" {log.n_rays:,} rays." in report  # counts read 2,880, as on the console
    assert "\n## Intensity\n" in report and "### Intensity by label" in report  # was 'Intensity (intensity)'
    assert "Intensity (intensity)" not in report
    assert (tmp_path / "flat" / "intensity_residuals.png").stat().st_size > 10_000
    assert "intensity_residuals.png" in (tmp_path / "flat" / "report.html").read_text()
    del log.attributes["intensity"]
    plain = compare(log, scene, flat, out=tmp_path / "plain")
    assert plain.intensity is None and "Intensity" not in (tmp_path / "plain" / "report.md").read_text()


def test_diagnose_report_carries_the_intensity_section(tmp_path):
    """The diagnosis page shows the final model's intensity residuals on the held-out rays."""
    scene, log = street_log(n_firings=120)
    diagnose(log, scene, SensorModel(), out=tmp_path, candidates=["range_bias"], steps=5, rounds=1)
    assert "\n## Intensity\n" in (tmp_path / "diagnosis.md").read_text()
    assert (tmp_path / "intensity_residuals.png").exists()
    assert np.isfinite(compare(log, scene, SensorModel()).intensity.metrics()["intensity_nll"])


def test_a_channel_is_named_once_when_the_attribute_is_intensity():
    """Headings and the CLI line read 'Intensity (intensity)' for a log's plain intensities."""
    empty = [np.zeros(0)] * 9
    assert IntensityResiduals("intensity", *empty).channel == "intensity"
    assert IntensityResiduals("reflectivity", *empty).channel == "intensity (reflectivity)"
