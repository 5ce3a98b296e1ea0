"""Fetch the Ouster SDK's test captures and their published digests (one per UDP lidar profile).

    python tools/fetch_ouster_sdk_data.py [--out DIR] [--from-git CLONE]

The files are the ouster-sdk repository's ``tests/pcaps`` captures (BSD-3-Clause, Ouster Inc.) at
a pinned commit, checked by SHA-256. They are test data, not part of mi-lidar: they go to
``../shared/data/ouster-sdk`` by default (where ``tests/io/test_ouster.py`` looks, or wherever
``$MI_LIDAR_OUSTER_SDK_DATA`` points) and the tests skip when they are absent.

* ``--from-git CLONE``: copy them from a local clone of ouster-lidar/ouster-sdk (``git show``)
  instead of downloading from GitHub.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import subprocess
import sys
import tempfile
import urllib.request
from pathlib import Path

COMMIT = "46b7bceee7995914e2f3f3facf4d78418335b2d7"
URL = "https://raw.githubusercontent.com/ouster-lidar/ouster-sdk/{commit}/tests/pcaps/{name}"
LICENSE_URL = f"https://github.com/ouster-lidar/ouster-sdk/blob/{COMMIT}/LICENSE"
FILES = {  # name -> SHA-256; profile in the comment
    "OS-2-32-U0_v2.0.0_1024x10.json": "78bf80ed91daa19e9ffde2be9168b9fe351cf55f801bf07d95183110af8054b9",  # LEGACY
    "OS-2-32-U0_v2.0.0_1024x10.pcap": "6a6b53d81de188d925241d9bddc2d5464798702b54490b6157fb9ecd057ec0ce",
    "OS-2-32-U0_v2.0.0_1024x10_digest.json": "ecf6b33df29f03d8c665af1fedc50c1f7b347d6c10c01c6e657ef2c382309bd8",
    "OS-2-128-U1_v2.3.0_1024x10.json": "7e77f644a80e998a9c60ac67309200c2b299fcaf6a140c8bec209af14372334a",  # RNG19
    "OS-2-128-U1_v2.3.0_1024x10.pcap": "66ef581f62f7cec8d8067efff38f46687672c6b39cdaa65095e795268d3362b5",
    "OS-2-128-U1_v2.3.0_1024x10_digest.json": "2752d6d157e4061f62de6fc2e7abbba6b2d2856a937255934b255d7e3eb114da",
    "OS-0-32-U1_v2.2.0_1024x10.json": "ce8c2dba389e3b3e4f5f6cb9ba2926628490c2cecf5b0caec92676e4ddd05ac2",  # DUAL
    "OS-0-32-U1_v2.2.0_1024x10.pcap": "a507e2d7b5337acb49e6c87a00225e55cdd6eb8531e972b1754755ace9252334",
    "OS-0-32-U1_v2.2.0_1024x10_digest.json": "a415f5701c8d7a88fa6c3c7398fd736699fb1651cf6bb4da4f91308fdd8b19b2",
    "OS-0-128-U1_v2.3.0_1024x10.json": "e51184ae7f7a2fd75b606e827badebd9cf937aeb60a5d07d336a91d9936272be",  # RNG15
    "OS-0-128-U1_v2.3.0_1024x10.pcap": "70b45e50cc07a14cae450538c03e4ff86a7aeed7d2be44e0fc1f5cb44e0c90a1",
    "OS-0-128-U1_v2.3.0_1024x10_digest.json": "462f0e05a7cd29ff5a82ea4da912c276f241ad097b55874feeda117894f09dc2",
}
DEFAULT_OUT = Path(__file__).resolve().parents[2] / "shared" / "data" / "ouster-sdk"


def _bytes_of(name: str, clone: Path | None) -> bytes:
    if clone is not None:
        return subprocess.run(
            ["git", "-C", str(clone), "show", f"{COMMIT}:tests/pcaps/{name}"], check=True, capture_output=True
        ).stdout
    url = URL.format(commit=COMMIT, name=name)
    try:
        with urllib.request.urlopen(url, timeout=60) as response:
            return response.read()
    except OSError as exc:
        raise SystemExit(f"{url}: download failed ({exc}); without network, use --from-git CLONE") from exc


def fetch(out: Path, clone: Path | None = None) -> list[Path]:
    """Write every file of :data:`FILES` into ``out`` (atomically, checked by SHA-256)."""
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for name, sha256 in FILES.items():
        target = out / name
        if target.is_file() and hashlib.sha256(target.read_bytes()).hexdigest() == sha256:
            continue
        data = _bytes_of(name, clone)
        found = hashlib.sha256(data).hexdigest()
        if found != sha256:
            raise SystemExit(f"{name}: SHA-256 {found} differs from the pinned {sha256}; not written")
        with tempfile.NamedTemporaryFile(dir=out, delete=False) as tmp:
            tmp.write(data)
        os.replace(tmp.name, target)
        written.append(target)
    (out / "README.md").write_text(
        f"Test captures of the Ouster SDK (ouster-lidar/ouster-sdk, tests/pcaps at {COMMIT}),\n"
        f"BSD-3-Clause, Copyright Ouster, Inc.: {LICENSE_URL}\nFetched by tools/fetch_ouster_sdk_data.py.\n"
    )
    return written


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"destination folder (default {DEFAULT_OUT})")
    parser.add_argument("--from-git", type=Path, default=None, help="a local clone of ouster-lidar/ouster-sdk")
    args = parser.parse_args(argv)
    written = fetch(args.out, args.from_git)
    print(f"{args.out}: {len(written)} files written, {len(FILES) - len(written)} already present")
    return 0


if __name__ == "__main__":
    sys.exit(main())
