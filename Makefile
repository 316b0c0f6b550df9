# forcecal — every command a user or CI runs. `make demo` and `make test` install
# what is missing (Debian packages + the project's venv) before they run.
SHELL := /bin/bash
.DEFAULT_GOAL := help

SCENE ?= scenes/liver.toml
OUT ?=
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.forcecal-setup
# libopenblas0-pthread: Debian's default libblas.so.3 / liblapack.so.3 (used by numpy, scipy,
# PETSc and MUMPS) is the unoptimised reference BLAS; installing OpenBLAS switches the
# alternative. Measured: a 1000^3 matmul 0.44 -> 0.045 s on one thread, the liver punch's FE
# indentation + relaxation at vertices 138 and 3 81.8 -> 54.1 s (same forces to 1e-15).
# OMP_NUM_THREADS=1 below keeps it to one thread per process (MPI ranks, calibration workers).
APT_PACKAGES := python3-dolfinx python3-gmsh python3-meshio python3-h5py python3-scipy \
	python3-numba python3-pytest python3-pytest-xdist python3-matplotlib python3-hypothesis \
	python3-tqdm python3-venv python3-pip-whl python3-setuptools-whl python3-wheel openmpi-bin \
	libopenblas0-pthread

# OpenMPI refuses to run as root without these; FFCx/numba caches go to a writable place.
export OMPI_ALLOW_RUN_AS_ROOT := 1
export OMPI_ALLOW_RUN_AS_ROOT_CONFIRM := 1
export OMPI_MCA_rmaps_base_oversubscribe := 1
export OMP_NUM_THREADS ?= 1
export XDG_CACHE_HOME ?= $(CURDIR)/.cache
export NUMBA_CACHE_DIR ?= $(CURDIR)/.cache/numba

STAGE_ARGS := --scene $(SCENE) $(if $(OUT),--out $(OUT))

.PHONY: help setup test demo validate reference calibrate gravity report bench bench-full bench-quick corpus corpus-recipe clean

help:
	@echo "make demo        # install what is missing, then mesh -> FE reference -> calibration -> gravity -> report"
	@echo "make validate    # demo, exit code 3 when the verdict fails (CI gate; SCENE=...)"
	@echo "make test        # install what is missing, then run the test suite"
	@echo "make reference | calibrate | gravity | report   # single stages (SCENE=... OUT=...)"
	@echo "make bench       # headline benchmarks, 8.5 min cold (measured, idle 2 cores) -> runs/bench-headline/ (bench-quick: a few minutes)"
	@echo "make bench-full  # every benchmark at full size, 1.5-2 h cold -> runs/bench/ (the committed bench.json)"
	@echo "make corpus      # every scenes/corpus/*.toml through the pipeline -> runs/corpus/corpus.json, docs/corpus.md"
	@echo "make corpus-recipe # the same with the README's own-mesh recipe -> runs/corpus_recipe/, docs/corpus_recipe.md"

setup: $(STAMP)

# Debian packages first (only the missing ones), then one venv that sees them,
# then the project itself, editable, with Debian's numpy/scipy/numba pinned.
$(STAMP): pyproject.toml constraints.txt Makefile
	@missing=""; for p in $(APT_PACKAGES); do \
	  dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "install ok installed" || missing="$$missing $$p"; \
	done; \
	if [ -n "$$missing" ]; then \
	  echo "setup: installing Debian packages:$$missing"; \
	  SUDO=""; [ "$$(id -u)" -eq 0 ] || SUDO=sudo; \
	  $$SUDO apt-get update -qq && \
	  DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq --no-install-recommends $$missing >/dev/null; \
	fi
	@[ -x $(PY) ] || /usr/bin/python3 -m venv --system-site-packages $(VENV)
	@$(PY) -m pip install -q --no-build-isolation --no-index -c constraints.txt -e . \
	  || $(PY) -m pip install -q --no-build-isolation -c constraints.txt -e .
	@$(PY) -c "import numpy, dolfinx, gmsh, h5py, numba, meshio; \
	  assert numpy.__version__ == '1.24.2', numpy.__version__; \
	  print('setup: dolfinx', dolfinx.__version__, '| numpy', numpy.__version__, '| numba', numba.__version__)"
	@touch $(STAMP)

# Two test processes, one per core (most tests run one single-threaded process); whole test
# files stay on one worker, so a module's fixtures are computed once. TEST_WORKERS=0 runs serially.
TEST_WORKERS ?= 2
test: setup
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile tests

demo: setup
	$(PY) -m pipelines demo $(STAGE_ARGS)

# the demo as a CI gate: exit code 3 when report.json's verdict fails, 0 when it passes
validate: setup
	$(PY) -m pipelines demo --require-pass $(STAGE_ARGS)

reference: setup
	$(PY) -m pipelines reference $(STAGE_ARGS)

calibrate: setup
	$(PY) -m pipelines calibrate $(STAGE_ARGS)

gravity: setup
	$(PY) -m pipelines gravity $(STAGE_ARGS)

report: setup
	$(PY) -m pipelines report $(STAGE_ARGS)

# make bench: the headline items (kernel, haptic, stability, run time vs error, FE convergence,
# scale), some reduced; make bench-full: every item at full size (what runs/bench/ holds)
bench: setup
	$(PY) -m pipelines bench --out runs/bench-headline

bench-full: setup
	$(PY) -m pipelines bench --full --out runs/bench

bench-quick: setup
	$(PY) -m pipelines bench --quick --out runs/bench-quick

corpus: setup
	$(PY) -m pipelines corpus

corpus-recipe: setup
	$(PY) -m pipelines corpus --recipe

clean:
	rm -rf $(VENV) .cache build *.egg-info
