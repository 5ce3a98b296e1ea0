# mi-lidar: two commands set everything up.
#   make demo   - set up (venv, Python packages, LLVM >= 16) and run the main job
#   make test   - set up and run the test suite (without tests marked `slow`)
SHELL := /bin/bash
VENV  := .venv
PY    := $(VENV)/bin/python
STAMP := $(VENV)/.installed
PYTEST_FLAGS ?= -n 2

.PHONY: setup demo test test-all bench clean llvm lint

setup: $(STAMP) llvm

$(STAMP): pyproject.toml
	@command -v python3 >/dev/null || { echo "mi-lidar needs python3 (>= 3.10) on PATH"; exit 1; }
	python3 -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[dev]"
	touch $(STAMP)

llvm:
	@bash tools/ensure_llvm.sh

demo: setup
	$(VENV)/bin/mi-lidar demo --out demo_out

lint: setup
	@bash tools/lint.sh

test: setup lint
	$(PY) -m pytest -m "not slow" $(PYTEST_FLAGS) -q

test-all: setup lint
	$(PY) -m pytest $(PYTEST_FLAGS) -q

bench: setup
	$(PY) -m pip install --quiet -e ".[bench]"
	@$(PY) -c "import open3d" 2>/dev/null || { echo "Open3D needs libusb-1.0: installing Debian's libusb-1.0-0"; \
		$$( [ "$$(id -u)" -ne 0 ] && echo sudo ) apt-get install -y -qq libusb-1.0-0 >/dev/null || \
		{ echo "could not install libusb-1.0-0; run: apt-get install -y libusb-1.0-0"; exit 1; }; }
	$(PY) -m bench

clean:
	rm -rf $(VENV) demo_out .pytest_cache
