"""tools/derive_carmen.py: bad sources and options get one line naming the value and the fix, and no output."""

import gzip
import importlib.util
import re
import sys
from pathlib import Path

import pytest

from .synth import carmen_text

TOOL = Path(__file__).resolve().parents[2] / "tools" / "derive_carmen.py"


@pytest.fixture(scope="module")
def tool():
    spec = importlib.util.spec_from_file_location("derive_carmen", TOOL)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def run(tool, monkeypatch, capsys, *args) -> tuple[int, str]:
    monkeypatch.setattr(sys, "argv", ["derive_carmen.py", *map(str, args)])
    try:
        tool.main()
    except SystemExit as exc:
        return exc.code, capsys.readouterr().err
    return 0, capsys.readouterr().out


def test_a_valid_log_is_derived(tool, monkeypatch, capsys, tmp_path):
    (tmp_path / "a.log").write_text(carmen_text(scans=4))
    code, out = run(tool, monkeypatch, capsys, tmp_path / "a.log", tmp_path / "b.log.gz", "--every", 2)
    assert code == 0 and "2 scans" in out
    assert gzip.decompress((tmp_path / "b.log.gz").read_bytes()).decode().count("FLASER 180 ") == 2


@pytest.mark.parametrize(
    "text, message",
    [
        # each of these was a traceback (ValueError, EOFError) or, for the last two, a silently broken output;
        # explicit ids: pytest-xdist workers must collect the same ids, and the gzip header holds a time stamp
        pytest.param(
            carmen_text(scans=2)[:-300],
            "line 6: FLASER with n=180 needs 190 fields .* repair or delete the line",
            id="cut-short",
        ),
        pytest.param(
            carmen_text(scans=2).replace(" 1.10 ", " nan ", 1), "line 4: FLASER value 'nan' is not finite", id="nan"
        ),
        pytest.param(
            "ODOM 0 0 0 0 0 0 1 host 1\n", r"no FLASER scans to write \(--scans :, --every 1\)", id="no-flaser"
        ),
        pytest.param(
            gzip.compress(carmen_text().encode(), mtime=0)[:8],
            "truncated gzip stream: it ends before any text",
            id="truncated-gzip",
        ),
    ],
)
def test_a_bad_source_is_named_and_nothing_written(tool, monkeypatch, capsys, tmp_path, text, message):
    source = tmp_path / "bad.log"
    source.write_bytes(text if isinstance(text, bytes) else text.encode())
    code, err = run(tool, monkeypatch, capsys, source, tmp_path / "out.log")
    assert code == 2 and err.startswith(f"error: {source}: "), err
    assert re.search(message, err), err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.log"]


@pytest.mark.parametrize(
    "options, message",
    [
        (["--every", "0"], "--every 0: must be >= 1"),  # ZeroDivisionError
        (["--every", "-1"], "--every -1: must be >= 1"),  # kept every scan
        (["--beams", "1"], "--beams 1: must be >= 2"),  # ZeroDivisionError
        (["--scans", "a:b"], "--scans 'a:b': give A:B"),  # ValueError
        (["--noise", "-0.1"], "--noise -0.1: must be >= 0"),  # no noise, silently
    ],
)
def test_bad_options_are_named(tool, monkeypatch, capsys, tmp_path, options, message):
    (tmp_path / "a.log").write_text(carmen_text(scans=2))
    code, err = run(tool, monkeypatch, capsys, tmp_path / "a.log", tmp_path / "b.log", *options)
    assert code == 2 and message in err, err
    assert not (tmp_path / "b.log").exists()


def test_missing_source_and_folder_target(tool, monkeypatch, capsys, tmp_path):
    code, err = run(tool, monkeypatch, capsys, tmp_path / "none.log", tmp_path / "b.log")
    assert code == 2 and "none.log: no such file; give a CARMEN .log or .log.gz" in err
    (tmp_path / "a.log").write_text(carmen_text(scans=2))
    code, err = run(tool, monkeypatch, capsys, tmp_path / "a.log", tmp_path)
    assert code == 2 and "is a folder; give the derived log's file name" in err
