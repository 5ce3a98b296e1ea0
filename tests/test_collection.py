"""Test ids are the same in every collection: pytest-xdist workers (`make test` runs `-n 2`) each collect the tree
and refuse to run when their ids differ ("Different tests were collected between gw0 and gw1")."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def collected_ids(hash_seed: str) -> list[str]:
    """The test ids of the whole tree, collected in a fresh interpreter with ``PYTHONHASHSEED=hash_seed``."""
    result = subprocess.run(
        [sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider", "tests"],
        cwd=REPO,
        env={**os.environ, "PYTHONHASHSEED": hash_seed},
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]
    return [line for line in result.stdout.splitlines() if "::" in line]


@pytest.mark.slow
def test_two_collections_give_the_same_ids():
    # Two interpreters with different string hashes (set order) and a few seconds apart (time stamps, such as the
    # one in a gzip header, that ended up in a parametrized id).
    first, second = collected_ids("1"), collected_ids("2")
    assert len(first) > 1000
    changed = sorted(set(first) ^ set(second))
    assert not changed, "\n".join(changed[:20])
    assert first == second  # the same order too: xdist compares the lists
