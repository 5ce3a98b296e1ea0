"""Variant selection and LLVM discovery, done once when :mod:`mi_lidar` is imported.

Dr.Jit's llvm backend needs LLVM >= 16. When ``DRJIT_LIBLLVM_PATH`` is unset we look for the
newest ``libLLVM`` >= 16 in the usual system folders and point Dr.Jit at it *before* Dr.Jit is
imported. The variant is ``$MI_LIDAR_VARIANT`` or ``llvm_ad_rgb``.
"""

from __future__ import annotations

import glob
import os
import re
import sys

from mi_lidar.core.errors import SetupError

DEFAULT_VARIANT = "llvm_ad_rgb"
MIN_LLVM_MAJOR = 16
_LLVM_GLOBS = (
    "/usr/lib/*/libLLVM*.so*",
    "/usr/lib/llvm-*/lib/libLLVM*.so*",
    "/usr/local/lib/libLLVM*.so*",
    "/usr/lib64/libLLVM*.so*",
)


def find_llvm() -> str | None:
    """Return the path of the newest system ``libLLVM`` with major version >= 16, or None."""
    best: tuple[int, str] | None = None
    for pattern in _LLVM_GLOBS:
        for path in glob.glob(pattern):
            match = re.search(r"(\d+)", os.path.basename(path))
            if match is None and "llvm-" in path:
                match = re.search(r"llvm-(\d+)", path)
            if match is None:
                continue
            major = int(match.group(1))
            if major >= MIN_LLVM_MAJOR and (best is None or major > best[0]):
                best = (major, path)
    return None if best is None else best[1]


def configure_llvm() -> None:
    """Set ``DRJIT_LIBLLVM_PATH`` to a suitable LLVM unless the user already did."""
    if os.environ.get("DRJIT_LIBLLVM_PATH"):
        return
    path = find_llvm()
    if path is not None:
        os.environ["DRJIT_LIBLLVM_PATH"] = path


def select_variant(mi) -> str:
    """Activate mi-lidar's variant in Mitsuba module ``mi`` and return its name.

    Keeps a JIT variant the user already selected (llvm or cuda); refuses scalar variants.
    """
    current = mi.variant()
    if current is not None and not current.startswith("scalar"):
        return current
    wanted = os.environ.get("MI_LIDAR_VARIANT", DEFAULT_VARIANT)
    if wanted.startswith("scalar"):
        raise SetupError(
            f"MI_LIDAR_VARIANT={wanted!r}: mi-lidar needs a JIT variant (llvm_ad_rgb or "
            "cuda_ad_rgb) because its plugins work on whole wavefronts of rays. "
            f"Unset MI_LIDAR_VARIANT or set it to {DEFAULT_VARIANT!r}."
        )
    if wanted not in mi.variants():
        raise SetupError(
            f"MI_LIDAR_VARIANT={wanted!r} is not a variant of this Mitsuba build; "
            f"choose one of {', '.join(v for v in mi.variants() if not v.startswith('scalar'))}."
        )
    try:
        mi.set_variant(wanted)
    except Exception as exc:  # Dr.Jit raises plain exceptions when LLVM or CUDA is missing.
        if wanted.startswith("cuda"):
            fix = (
                "The cuda variants need an NVIDIA GPU and its driver (libcuda.so), and none could be used here. "
                f"Unset MI_LIDAR_VARIANT or set it to {DEFAULT_VARIANT!r} to run on the CPU."
            )
        else:
            fix = (
                "Dr.Jit's llvm backend needs LLVM >= 16. Run `make demo` (it installs Debian's "
                "libllvm19) or `apt-get install -y libllvm19`, or set DRJIT_LIBLLVM_PATH to a "
                "libLLVM.so of version 16 or newer."
            )
        first_line = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise SetupError(f"could not start Mitsuba variant {wanted!r} ({first_line}). {fix}") from exc
    return wanted


def exit_if_command_line(error: SetupError) -> None:
    """When the ``mi-lidar`` command is starting, print ``error`` on one line and exit with code 2.

    The command imports :mod:`mi_lidar` (which selects the variant) before its own error handler
    exists, so a setup error would otherwise end in a traceback. Library users get the exception.
    """
    if os.path.basename(sys.argv[0]) == "mi-lidar":
        print(f"error: {error}", file=sys.stderr)
        raise SystemExit(2)


def require_jit_variant(mi) -> None:
    """Raise :class:`SetupError` when a scalar variant is active (plugins cannot run there)."""
    variant = mi.variant()
    if variant is None or variant.startswith("scalar"):
        raise SetupError(
            f"mi-lidar plugins need a JIT variant, but the active Mitsuba variant is {variant!r}. "
            f"Call mi.set_variant({DEFAULT_VARIANT!r}) (or another llvm_/cuda_ variant) first."
        )
