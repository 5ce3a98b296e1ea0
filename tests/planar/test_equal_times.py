"""A planar log whose scans all have one timestamp (a converter that wrote no times) is prepared with a warning."""

import warnings

import pytest

from mi_lidar.core.errors import EqualTimesWarning
from mi_lidar.io.carmen import read_carmen
from mi_lidar.planar.protocol import PlanarProtocol, prepare
from tests.planar.world import room_log_text

PROTOCOL = PlanarProtocol(radius=1.0, window=30.0, batch=16)


def room_at(tmp_path, stamp: float | None):
    """The 10-scan room drive, its scans all timed ``stamp`` s (None: 0.2 s apart, as written)."""
    lines = room_log_text(scans=10).splitlines()
    if stamp is not None:
        lines = [" ".join(t[:-3] + [f"{stamp:f}", t[-2], f"{stamp:f}"]) for t in map(str.split, lines[1:])]
    (tmp_path / "room.log").write_text("\n".join(lines) + "\n")
    return read_carmen(tmp_path / "room.log")


@pytest.mark.parametrize("stamp", [0.0, 1234.5])
def test_equal_timestamps_widen_the_leave_out_and_are_said(tmp_path, stamp):
    log = room_at(tmp_path, stamp)
    with pytest.warns(EqualTimesWarning) as said:
        data = prepare(log, PROTOCOL, workers=1)
    assert len(said) == 1
    assert " ".join(str(said[0].message).split()) == (
        f"{tmp_path / 'room.log'}: all 10 scans have the timestamp {stamp:g} s (a converter that wrote no times?), so "
        "each scan's map leaves out every scan within 1 m of it whatever its time, not only those within 30 s: a "
        "wider leave-out than the protocol's. Give the log its real timestamps"
    )
    assert data.test.nominal.size > 0


def test_timestamps_that_differ_are_prepared_silently(tmp_path):
    log = room_at(tmp_path, None)
    with warnings.catch_warnings():
        warnings.simplefilter("error", EqualTimesWarning)
        prepare(log, PROTOCOL, workers=1)
