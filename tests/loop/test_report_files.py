"""compare's report folder holds exactly the files it reports, also when it is written again: no temporaries."""

import numpy as np

from mi_lidar.core.patterns import get_pattern
from mi_lidar.loop import compare
from mi_lidar.scene.simulation import simulate

from .helpers import street


def test_compare_report_rewritten_leaves_no_temporary_files(tmp_path):
    scene, model, poses = street(1)
    log = simulate(scene, get_pattern("vlp16", n_firings=90), poses=poses, model=model, seed=3)
    out = tmp_path / "report"
    first = compare(log, scene, model, out=out)
    second = compare(log, scene, model, out=out, seed=1)
    names = sorted(p.name for p in out.iterdir())
    assert names == sorted(p.name for p in second.files) == sorted(p.name for p in first.files)
    assert {"comparison.json", "report.md", "report.html"} <= set(names)
    assert not [n for n in names if ".tmp" in n or n.startswith(".")]
    assert np.isfinite(second.headline["nll"])
