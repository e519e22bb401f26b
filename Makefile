# Two entry points for a fresh machine: `make demo` and `make test`.
PYTHON ?= python3.11
# torch is installed first and pinned, so no resolver ever pulls a multi-GB CUDA build on
# a CPU machine (the dev machines and CI have this CPU build on disk).
TORCH  ?= torch==2.13.0
PIP    := -m pip install -qq

# .venv: the full install (core + Blender for rendering + test tools, selenium for the browser
# tests; numpy <2 for bpy).
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

# .venv-core: the core install without Blender (numpy 2), for `make test-core`.
CORE_VENV  := .venv-core
CORE_PY    := $(CORE_VENV)/bin/python
CORE_STAMP := $(CORE_VENV)/.installed

# build/venvs: for `make test-versions`, Python 3.12 and 3.13 with the core requirements
# except torch and dvc.
VERSION_VENVS ?= build/venvs
NEWER_PYTHONS ?= 3.12 3.13

.PHONY: setup setup-core demo test test-core test-versions bench clean-venv

setup: $(STAMP)

setup-core: $(CORE_STAMP)

# Re-run only when the dependency list changes.
$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) $(PIP) --upgrade pip
	$(PY) $(PIP) $(TORCH)
	$(PY) $(PIP) -e '.[render,dev,browser]'
	@touch $@

$(CORE_STAMP): pyproject.toml
	@test -x $(CORE_PY) || $(PYTHON) -m venv $(CORE_VENV)
	$(CORE_PY) $(PIP) --upgrade pip
	$(CORE_PY) $(PIP) $(TORCH)
	$(CORE_PY) $(PIP) -e '.[dev]'
	@touch $@

demo: setup
	$(VENV)/bin/cnnps demo

test: setup
	$(PY) -m pytest -q

# The suite in the core install: tests marked `blender` skip (tests/conftest.py), all
# others must pass with numpy 2 and without bpy.
test-core: setup-core
	$(CORE_PY) -c 'import importlib.util as u, numpy; \
	assert u.find_spec("bpy") is None, "bpy is installed in $(CORE_VENV)"; \
	assert int(numpy.__version__.split(".")[0]) >= 2, "numpy " + numpy.__version__ + " in $(CORE_VENV)"; \
	print("$(CORE_VENV): no bpy, numpy", numpy.__version__)'
	$(CORE_PY) -m pytest -q

# The core install on the newer Pythons (tests/test_python_versions.py): for each of
# $(NEWER_PYTHONS) found on PATH or under pyenv, an environment in $(VERSION_VENVS) with the
# core requirements except torch and dvc (from PyPI; torch is never installed there), then
# the metadata and torch-free import checks with those interpreters. A version not found
# is reported and its tests skip.
test-versions: setup-core
	pythons="$$($(CORE_PY) -m tests.support.pythons $(VERSION_VENVS) $(NEWER_PYTHONS))" && \
	CNNPS_TEST_PYTHONS="$$pythons" $(CORE_PY) -m pytest -q -rs tests/test_python_versions.py

# A quick set of benchmarks, one or two an area at small sizes (a few minutes on 2 cores),
# written to $(BENCH_OUT) rather than the committed benchmarks/results/; every benchmark,
# what it needs and how to run it: benchmarks/README.md.
BENCH_OUT ?= build/bench
BENCH     := $(PY) -m benchmarks

bench: setup
	$(BENCH).predict.obsmap_speed --pixels 4000 --repeat 3 --no-ball --out $(BENCH_OUT)/predict/obsmap_speed.json
	$(BENCH).predict.inference_speed --pixels 2000 --maps 512 --repeat 3 --no-k10 --no-ball \
	    --out $(BENCH_OUT)/predict/inference_speed.json
	$(BENCH).train.layer_bound --threads 1 --batch 16 --repeat 3 --out $(BENCH_OUT)/train/layer_bound.json
	$(BENCH).synth.pixelwise_maps --skip-render --repeat 2 --out $(BENCH_OUT)/synth/pixelwise_maps.json
	$(BENCH).io.extract_speed --pixels 1024 --lights 96 --repeat 2 --out $(BENCH_OUT)/io/extract_speed.json
	$(BENCH).pipeline.integrate_speed_accuracy --megapixels 0.05 --repeat 3 \
	    --out $(BENCH_OUT)/pipeline/integrate_speed_accuracy.json
	@echo "quick set done, results in $(BENCH_OUT)/. The other benchmarks (full sizes, real data," \
	    "Blender, training runs) and how to run each: benchmarks/README.md"

clean-venv:
	rm -rf $(VENV) $(CORE_VENV) $(VERSION_VENVS)
