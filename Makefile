# freeform — every command installs what it needs first.
#   make test    install (if needed) and run the test suite
#   make train   install (if needed) and run the default training (a CPU-sized demo)
# Choose your torch: `make install TORCH="torch==2.13.0 --index-url https://download.pytorch.org/whl/cu128"`.
PYTHON ?= python3
VENV   ?= .venv
TORCH  ?= torch==2.13.0
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: install test train bench lint clean reproduce

install: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q $(TORCH)
	$(BIN)/python -m pip install -q -e ".[dev]"
	touch $(STAMP)

# The suite runs the physics on the strict path (fast-math off: the same bits on any x86-64 CPU; the reference tests
# hold there). The simulator's tests run again with fast-math on (the production path; reference tests skip) and
# on the quadrants backend (Taichi's fork; one backend per process). docs/physics-running.md, "Host independence".
# Each stage runs on JOBS pytest-xdist workers (whole files per worker: a module's kernels compile once there), one
# torch thread each so that the workers do not fight over the cores; files in the order tests/conftest.py gives
# (those with a `slow` test first), not xdist's by test count.
JOBS      ?= 2
PYTEST    := OMP_NUM_THREADS=1 $(BIN)/python -m pytest -q -n $(JOBS) --dist loadfile --no-loadscope-reorder
SIM_TESTS := tests/test_sim_api.py tests/test_sim_numerics.py tests/test_sim_physics.py tests/test_terrain.py tests/test_packing.py

test: install
	$(BIN)/python -m ruff check freeform tests benchmarks experiments scripts lab  # (pinned: a newer ruff's rules do not fail CI)
	$(PYTEST) tests
	FREEFORM_FAST_MATH=1 $(PYTEST) $(SIM_TESTS) tests/test_native.py
	FREEFORM_BACKEND=quadrants $(PYTEST) $(SIM_TESTS) tests/test_sim_command.py

train: install
	$(BIN)/freeform-train

bench: install
	$(BIN)/python -m benchmarks

# The paper's sweeps (5 seeds of paper_volume and paper_locomotion, GPU) and every figure: docs/experiments.md.
# SKIP_TRAIN=1 only redraws the figures from existing runs.
reproduce: install
	PYTHON=$(abspath $(BIN)/python) bash experiments/reproduce.sh

lint: install
	$(BIN)/python -m ruff check freeform tests benchmarks experiments scripts lab

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .ruff_cache outputs multirun runs
	find . -name __pycache__ -type d -prune -exec rm -rf {} +
