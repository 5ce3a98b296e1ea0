#!/usr/bin/env bash
# Make sure an LLVM >= 16 shared library is present for Dr.Jit's llvm backend.
# On Debian/Ubuntu without one, install Debian's libllvm19 (needs root and apt-get).
set -uo pipefail

have_llvm() {
    local f v
    for f in /usr/lib/*/libLLVM*.so* /usr/lib/llvm-*/lib/libLLVM*.so* /usr/local/lib/libLLVM*.so*; do
        [ -e "$f" ] || continue
        v=$(basename "$f" | grep -oE '[0-9]+' | head -n 1)
        if [ -n "$v" ] && [ "$v" -ge 16 ]; then echo "$f"; return 0; fi
    done
    return 1
}

if [ -n "${DRJIT_LIBLLVM_PATH:-}" ] && [ -e "$DRJIT_LIBLLVM_PATH" ]; then exit 0; fi
if have_llvm >/dev/null; then exit 0; fi

echo "mi-lidar: no LLVM >= 16 found (Dr.Jit's llvm backend needs it); installing Debian's libllvm19 ..."
if [ "$(id -u)" -ne 0 ]; then SUDO=sudo; else SUDO=; fi
if command -v apt-get >/dev/null; then
    $SUDO apt-get update -qq && $SUDO apt-get install -y -qq libllvm19 >/dev/null
fi
if have_llvm >/dev/null; then
    echo "mi-lidar: using $(have_llvm)"; exit 0
fi
cat >&2 <<'MSG'
mi-lidar: could not install an LLVM >= 16 library.
  Dr.Jit's llvm backend needs one (LLVM 15 and older abort with "Cannot select ... fminimum").
  On Debian/Ubuntu run, as root:   apt-get update && apt-get install -y libllvm19
  Elsewhere install LLVM 16+ and point Dr.Jit at it:
      export DRJIT_LIBLLVM_PATH=/path/to/libLLVM.so
MSG
exit 1
