"""Dr.Jit's on-disk kernel cache under concurrent dataset workers.

Two processes render the same frames at once into one empty cache folder (``DRJIT_CACHE_DIR``), so
they compile and write the same kernels concurrently; a third process then renders them again. Each
process must compile a kernel once (its second frame compiles nothing), the cache must hold no
partial file, and the third process must load every kernel the cache holds (none discarded, none
compiled again) and write the same bytes.

A process may still compile a kernel the cache lacks: Dr.Jit writes the alignment of some scalar
inputs (``align 1`` or ``align 4``, from where they happen to lie in memory) into the kernel's
source, so one Lidar kernel comes in a few variants, each compiled once and then cached.
"""

import json
import os
import subprocess
import sys

import pytest

from tests.conftest import SCENES

SPEC = f"""
name: cache
seed: 3
rig:
  lidars: [{{name: top, pattern: vlp16, mount: {{xyz: [0, 0, 1.8]}}}}]
  cameras: [{{name: front, width: 64, height: 40, mount: {{xyz: [0.5, 0, 1.6]}}}}]
scenes:
  - name: street
    xml: {SCENES / "urban_street.xml"}
    frames: 2
    labels: {{1: road, 2: building, 3: pole, 4: car, 6: vegetation}}
    trajectory: {{waypoints: [[-6, 0], [4, 0]]}}
output: {{spp: 2}}
"""
RENDER = """
import json, sys
import drjit as dr
from mi_lidar.dataset import load_spec
from mi_lidar.dataset.run import frame_task

dr.set_flag(dr.JitFlag.KernelHistory, True)
spec = load_spec(sys.argv[1])
frames = []
for index in range(spec.frames):
    record = frame_task(spec, sys.argv[2], index)
    kernels = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
    frames.append({
        "kernels": len(kernels),
        "compiled": [k["hash"] for k in kernels if not k["cache_hit"]],
        "from_disk": sum(bool(k["cache_disk"]) for k in kernels),
        "files": record["files"],
    })
print(json.dumps(frames))
"""


def render(spec, out, cache) -> subprocess.Popen:
    env = {**os.environ, "DRJIT_CACHE_DIR": str(cache)}
    command = [sys.executable, "-c", RENDER, str(spec), str(out)]
    return subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def finish(process) -> tuple[list[dict], str]:
    stdout, stderr = process.communicate()
    assert process.returncode == 0, stderr[-3000:]
    return json.loads(stdout.strip().splitlines()[-1]), stderr


@pytest.mark.slow
def test_concurrent_workers_share_the_kernel_cache_safely(tmp_path):
    spec, cache = tmp_path / "spec.yaml", tmp_path / "cache"
    spec.write_text(SPEC)
    cache.mkdir()
    first = [render(spec, tmp_path / f"out{i}", cache) for i in range(2)]  # compile the same kernels at once
    runs = [finish(p) for p in first]
    for frames, _ in runs:
        assert frames[0]["compiled"] and not frames[1]["compiled"], frames  # each compiles a kernel once
    cached = {p.name.split(".")[0] for p in cache.iterdir()}
    assert not [p.name for p in cache.iterdir() if ".tmp" in p.name], "partial cache files left"
    frames, stderr = finish(render(spec, tmp_path / "out2", cache))
    assert not set(frames[0]["compiled"] + frames[1]["compiled"]) & cached, "a cached kernel was compiled again"
    assert frames[0]["from_disk"] > 0
    assert "discarding" not in stderr and "jit_kernel" not in stderr, stderr[-2000:]
    for other, _ in runs:
        assert [f["files"] for f in other] == [f["files"] for f in frames]
