"""Robustness of every reader: seeded mutants either read or raise the documented error naming the file.

The short run (30 mutants per reader) is part of ``make test``; the long run (1000 per reader,
``slow``) prints the outcome table. See :mod:`tests.io.fuzzing` for the mutations and the worker
process that detects hangs (a read longer than 5 s) and crashes.
"""

import numpy as np
import pytest

from mi_lidar.core.densities.base import ReturnDensity
from mi_lidar.core.log import Log

from .fuzzing import READERS, Worker, build_seeds, failure_report, fuzz, table

SHORT_RUN = 30
LONG_RUN = 1000


@pytest.fixture(scope="module")
def seeds(tmp_path_factory):
    return build_seeds(tmp_path_factory.mktemp("seeds"))


@pytest.fixture(scope="module")
def worker(seeds):
    one = Worker(seeds)
    yield one
    one.stop()


def test_seeds_read_cleanly(seeds):
    for name, reader in READERS.items():
        result = reader.read(seeds / reader.seed, seeds)
        if name.startswith("poses"):
            assert result.shape == (4, 4, 4), name
        elif name.startswith("density"):
            assert isinstance(result, ReturnDensity) and result.name == name.split("-", 1)[1].replace("-", "_"), name
        elif name.startswith("pattern"):
            assert result.shape == (16, 8), name
        elif name == "annotation":
            (objects, ground), (sensor, poses) = result
            assert len(objects) == 1 and len(ground.faces) == 1 and sensor.pattern == "vlp16" and len(poses) == 1
        elif name.startswith("library"):
            assert sorted(p.id for p in result.primitives) == ["rock", "tree"], name
        elif name != "scene-xml":
            assert isinstance(result, Log) and result.n_rays > 0, name


def test_empty_files_are_reported(seeds, tmp_path):
    for name, reader in READERS.items():
        path = tmp_path / name
        path.mkdir()
        empty = path / (seeds / reader.seed).name
        if reader.bag:
            for companion in (seeds / reader.seed).parent.iterdir():
                (path / companion.name).write_bytes(companion.read_bytes())
        empty.write_bytes(b"")
        with pytest.raises(reader.errors) as caught:
            reader.read(empty, seeds)
        assert empty.name in str(caught.value) or path.name in str(caught.value), name


def test_mutations_are_seeded_and_varied(seeds):
    from .fuzzing import mutant_bytes

    original = (seeds / READERS["las"].seed).read_bytes()
    mutants = [mutant_bytes(seeds, "las", 0, i) for i in range(30)]
    assert mutants == [mutant_bytes(seeds, "las", 0, i) for i in range(30)]
    assert len(set(mutants)) == 30 and original not in mutants
    lengths = np.array([len(m) for m in mutants])
    assert (lengths < len(original)).any() and (lengths > len(original)).any()


@pytest.mark.parametrize("name", list(READERS))
def test_mutants_read_or_raise_the_documented_error(worker, name):
    tallies = fuzz([worker], [name], SHORT_RUN, seed=0)
    assert sum(tallies[name].counts.values()) == SHORT_RUN
    assert tallies[name].failures == 0, failure_report(tallies)


@pytest.mark.slow
def test_long_fuzz_run(seeds, capsys):
    workers = [Worker(seeds), Worker(seeds)]
    try:
        tallies = fuzz(workers, list(READERS), LONG_RUN, seed=1)
    finally:
        for one in workers:
            one.stop()
    with capsys.disabled():
        print(f"\nfuzzing every reader, {LONG_RUN} mutants each (hang limit 5 s)\n{table(tallies)}")
    assert all(sum(t.counts.values()) == LONG_RUN for t in tallies.values())
    assert sum(t.failures for t in tallies.values()) == 0, failure_report(tallies)
