# SurfPhase: `make demo` runs the pipeline on the embedded synthetic demo campaign,
# `make test` runs the test suite. Each creates .venv and installs what it needs.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp
CORES ?= 2
# Python keeps each module's compiled bytecode (__pycache__, git-ignored). An environment
# that exports PYTHONDONTWRITEBYTECODE (some sandboxes and CI images do) otherwise makes
# every one of a run's Python processes (each workflow job, each pytest worker, which
# also rewrites every test module's asserts) compile its sources again.
unexport PYTHONDONTWRITEBYTECODE

.PHONY: install test lint demo demo-data clean-demo

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --upgrade pip
	# Pin torch first: the CPU wheel on disk; any other request pulls CUDA packages.
	$(BIN)/python -m pip install torch==2.13.0
	$(BIN)/python -m pip install -e '.[test]'
	touch $(STAMP)

install: $(STAMP)

lint: $(STAMP)
	$(BIN)/ruff check surfphase tests
	$(BIN)/snakemake --lint --cores 1

# The renderer's numba kernels are compiled (or loaded from their cache) once, before the
# parallel test workers and workflow jobs that would otherwise each compile them.
KERNELS := $(BIN)/python -c "from surfphase.render.fused import compile_kernels; compile_kernels()"

test: $(STAMP) lint
	$(KERNELS)
	$(BIN)/python -m pytest -q -n 2 --dist loadfile

# The demo campaign is generated once (written whole; demo/synth.json is its last file):
# a second `make demo` reuses it and Snakemake reruns only what is out of date.
demo/synth.json: | $(STAMP)
	$(BIN)/surfphase synth --preset demo --out demo

demo-data: demo/synth.json

demo: demo-data
	$(KERNELS)
	$(BIN)/snakemake --cores $(CORES) --keep-going --rerun-incomplete
	$(BIN)/snakemake --report results/report.html
	@echo "Report: results/report.html; campaign page: results/campaign/index.html;"
	@echo "metrics: results/campaign/metrics.csv (see README.md for every output)."

clean-demo:
	rm -rf demo results logs benchmarks .snakemake
