#!/usr/bin/env bash
# Static contracts of the code base, run by `make lint` (and so by `make test`):
#   ruff (lint + format check), import-linter (layers point down), mypy (the core package).
# import-linter reads the package from disk, and `plugins/` and `calibration/` are mapped into the
# `mi_lidar` namespace only by setuptools' package-dir: the check runs on a staged copy of the tree.
set -euo pipefail
cd "$(dirname "$0")/.."
BIN=${BIN:-.venv/bin}
"$BIN/ruff" check .
"$BIN/ruff" format --check .
stage=$(mktemp -d)
trap 'rm -rf "$stage"' EXIT
cp -r mi_lidar "$stage/mi_lidar"
cp -r plugins "$stage/mi_lidar/plugins"
cp -r calibration "$stage/mi_lidar/calibration"
(cd "$stage" && PYTHONPATH="$stage" "$OLDPWD/$BIN/lint-imports" --config "$OLDPWD/pyproject.toml")
"$BIN/mypy"
