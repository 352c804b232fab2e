# Two entry points on a fresh Debian machine: `make demo` and `make test`.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
LLVM19 := /usr/lib/x86_64-linux-gnu/libLLVM-19.so
SUDO   := $(shell [ "$$(id -u)" = 0 ] || echo sudo)

.PHONY: all setup llvm demo test test-slow bench clean cycles gltf-validator chromium

all: setup

# Dr.Jit's LLVM backend needs LLVM >= 16 (Debian 12 ships 14/15, which abort on `fminimum`).
llvm:
	@if [ -n "$$DRJIT_LIBLLVM_PATH" ] || ls /usr/lib/x86_64-linux-gnu/libLLVM-1[6-9]*.so* /usr/lib/x86_64-linux-gnu/libLLVM-[2-9][0-9]*.so* \
	     /usr/lib/llvm-1[6-9]/lib/libLLVM*.so* /usr/lib/llvm-[2-9][0-9]/lib/libLLVM*.so* 2>/dev/null | grep -q .; then \
	  echo "LLVM >= 16 for Dr.Jit: found"; \
	else \
	  echo "Installing libllvm19 (needed by Dr.Jit's LLVM backend)"; \
	  $(SUDO) apt-get update -qq && $(SUDO) apt-get install -y -qq libllvm19; \
	fi

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	@# CPU-only machines take the CPU torch build; an unpinned torch pulls GBs of CUDA packages.
	@if command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; then \
	  $(PY) -m pip install -q "torch>=2.3"; \
	else \
	  $(PY) -m pip install -q "torch==2.13.0"; \
	fi
	$(PY) -m pip install -q -e ".[dev]"
	touch $@

setup: llvm $(VENV)/.installed

# Re-running skips what is done: the dataset is kept, a finished fit is not redone, an
# interrupted one resumes from its checkpoint.
demo: setup
	@[ -f data/demo/scene.json ] || $(VENV)/bin/vq-mitsuba make-scene demo -o data/demo
	$(VENV)/bin/vq-mitsuba fit data/demo/scene.xml -o runs/demo --preset demo \
	  $$([ -f runs/demo/checkpoint.pt ] && echo --resume)
	$(VENV)/bin/vq-mitsuba render runs/demo --cameras data/demo/transforms_test.json -o runs/demo/test_views
	@echo "Demo results: runs/demo (materials.json, materials_sheet.png, materials_err.png, envmap.exr, loss.png)"
	@echo "  and runs/demo/test_views (novel views, maps, NAME_material.png ids, NAME_segmentation.png overlays)"

# Blender as a module for `make-scene --renderer cycles`: bpy needs Python 3.11 and numpy < 2, so it
# gets its own environment; the Cycles worker runs there as a subprocess.
CYCLES_VENV := .venv-cycles

$(CYCLES_VENV)/.installed:
	$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info[:2] == (3, 11) else "bpy 5.0 needs Python 3.11 (set PYTHON=python3.11)")'
	$(PYTHON) -m venv $(CYCLES_VENV)
	$(CYCLES_VENV)/bin/pip install -q "bpy==5.0.1" "numpy<2"
	touch $@

cycles: $(CYCLES_VENV)/.installed

# The Khronos glTF validator (npm) checks the exported .glb files in the tests.
NODE_DIR := .node

$(NODE_DIR)/.installed:
	@command -v npm >/dev/null 2>&1 || { echo "Installing Node.js and npm (for the glTF validator)"; \
	  $(SUDO) apt-get update -qq && $(SUDO) apt-get install -y -qq nodejs npm; }
	npm install --silent --no-audit --no-fund --prefix $(NODE_DIR) gltf-validator@2.0.0-dev.3.10
	touch $@

gltf-validator: $(NODE_DIR)/.installed

# Headless Chromium (Debian's packages) drives the editor page in the tests through Selenium.
chromium:
	@if command -v chromium >/dev/null 2>&1 && command -v chromedriver >/dev/null 2>&1; then \
	  echo "Chromium and chromedriver: found"; \
	else \
	  echo "Installing chromium and chromium-driver (for the editor's browser test)"; \
	  $(SUDO) apt-get update -qq && $(SUDO) apt-get install -y -qq chromium chromium-driver; \
	fi

# The Cycles ground-truth path is part of the product: its environment is set up too, so its tests run.
test: setup cycles gltf-validator chromium
	$(PY) -m pytest -q -rs

test-slow: setup
	$(PY) -m pytest -q -m slow

bench: setup
	$(PY) benchmarks/bench_scenes.py

clean:
	rm -rf runs data benchmarks/out $(NODE_DIR)
