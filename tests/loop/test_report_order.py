"""Breakdown groups sort numerically, and relative gains are reported only where meaningful."""

import math

import numpy as np

from mi_lidar.loop.compare import RayTable, breakdown, gain_groups
from mi_lidar.loop.selection import relative_gain


def table(azimuth: np.ndarray) -> RayTable:
    n = azimuth.size
    zeros, ones = np.zeros(n), np.ones(n, bool)
    return RayTable(
        ll=-np.arange(n, dtype=float),
        measured=zeros + 5,
        hit=ones,
        sim_range=zeros + 5,
        sim_hit=ones,
        nominal=zeros + 5,
        cos_incidence=zeros + 1,
        kind=np.zeros(n, int),
        label=np.zeros(n, int),
        shape=np.zeros(n, int),
        beam=np.arange(n) % 12,
        column=np.arange(n),
        scan=np.zeros(n, int),
        azimuth=azimuth,
    )


def test_azimuth_and_beam_groups_sort_numerically():
    t = table(np.linspace(-179, 179, 24))
    groups = [r["group"] for r in breakdown(t, "azimuth")]
    starts = [int(g.split("..")[0]) for g in groups]
    assert starts == sorted(starts) and starts[0] == -180 and len(groups) == 12
    beams = [r["group"] for r in breakdown(t, "beam")]
    assert beams == [f"beam {b:03d}" for b in range(12)]


def test_range_groups_sort_numerically_and_the_last_is_open():
    """The last range group read ``80-1e+09 m`` in the breakdown figure and tables."""
    t = table(np.zeros(9))
    t.nominal[:] = [0.5, 1.5, 3, 7, 15, 30, 60, 120, np.nan]
    groups = [r["group"] for r in breakdown(t, "range")]
    assert groups == ["0-1 m", "1-2 m", "2-5 m", "5-10 m", "10-20 m", "20-40 m", "40-80 m", "80+ m", "none"]


def test_relative_gain_only_away_from_zero_nll():
    assert relative_gain(0.5, -2.0) == 25.0
    assert math.isnan(relative_gain(0.5, 0.3))


def test_a_group_is_named_with_its_breakdown_once():
    """``compare`` printed ``worst: label label 2``: the label, beam, shape and time groups already say what they
    count; the others take the breakdown's name."""
    from mi_lidar.loop.compare import BREAKDOWNS, group_keys, group_name

    t = table(np.linspace(-179, 179, 24))
    names = {by: group_name({"breakdown": by, "group": str(group_keys(t, by)[0])}) for by in BREAKDOWNS}
    assert names["label"] == "label 0" and names["beam"] == "beam 000" and names["shape"] == "shape 0"
    assert names["time"] == "scan 0" and names["range"] == "range 5-10 m"
    assert names["incidence"] == "incidence 00-15 deg" and names["element_type"] == "element type surface"
    assert group_name({"breakdown": "label", "group": "none"}) == "label none"


def test_gain_groups_name_where_the_gain_concentrates_one_group_per_breakdown():
    t = table(np.linspace(-179, 179, 240))
    before = np.full(240, -3.0)
    after = before.copy()
    after[t.beam == 5] += 2.0  # beam 5 gains 2 nats per ray; a small gain everywhere else
    after[t.beam != 5] += 0.01
    rows = gain_groups(t, before, after)
    assert rows[0]["breakdown"] == "beam" and rows[0]["group"] == "beam 005"
    assert rows[0]["rays"] == 20 and math.isclose(rows[0]["gain"], 40.0)
    assert math.isclose(rows[0]["nll_before"] - rows[0]["nll_after"], 2.0)
    assert len({r["breakdown"] for r in rows}) == len(rows) <= 3  # one group per breakdown
    gains = [r["nll_before"] - r["nll_after"] for r in rows]
    assert gains == sorted(gains, reverse=True)


def test_time_groups_name_their_first_and_last_scan():
    """The time groups read ``scans 00182``, which names one scan, for a group of 91 scans."""
    t = table(np.zeros(910))
    t.scan = np.arange(910)
    groups = [r["group"] for r in breakdown(t, "time")]
    assert groups[:3] == ["scans 0-90", "scans 91-181", "scans 182-272"] and groups[-1] == "scans 819-909"
    assert all(r["rays"] == 91 for r in breakdown(t, "time"))
    t.scan = np.arange(910) % 5
    assert [r["group"] for r in breakdown(t, "time")] == [f"scan {s}" for s in range(5)]
