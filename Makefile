# Two commands on a fresh machine: `make demo` and `make test`.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# the Franka emulator's simulator (franka-sim pins numpy 1.26 and MuJoCo < 3.3): an environment of its own
SIM_VENV := .venv-franka-sim
SIM_STAMP := $(SIM_VENV)/.installed
SIM_REQ := mocks/franka/requirements-sim.txt

.PHONY: venv franka-sim demo test lint bench clean

$(STAMP): pyproject.toml setup.py
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[dev]'
	touch $(STAMP)

venv: $(STAMP)

$(SIM_STAMP): $(SIM_REQ)
	test -x $(SIM_VENV)/bin/python || $(PY) -m venv $(SIM_VENV)
	$(SIM_VENV)/bin/python -m pip install -q --upgrade pip
	$(SIM_VENV)/bin/python -m pip install -q -r $(SIM_REQ)
	touch $(SIM_STAMP)

franka-sim: $(SIM_STAMP)

demo: $(STAMP)
	$(BIN)/station demo

# two parts: everything that tolerates a neighbour, two at a time on the two cores (whole files per worker:
# module fixtures stay shared), then the tests that time the wire or load the machine (soak), alone
# bytecode caches on for the test run (a host may set PYTHONDONTWRITEBYTECODE): else every pytest process
# rewrites and compiles all test modules again (~10 s of CPU each) and every station subprocess its modules
test test-matrix: export PYTHONDONTWRITEBYTECODE :=
test: $(STAMP) $(SIM_STAMP)
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -q -n 2 --dist loadfile -m "not exclusive and not fullmatrix" --durations=25
	$(BIN)/python -m pytest -q -m exclusive --durations=10

# every fault on every bus (make test runs each fault once, on one bus, through all four phases)
test-matrix: $(STAMP)
	$(BIN)/python -m pytest -q -n 2 -m fullmatrix tests/e2e/test_fault_matrix.py

lint: $(STAMP)
	$(BIN)/ruff check .

bench: $(STAMP)
	$(BIN)/python bench/solver.py

clean:
	rm -rf $(VENV) $(SIM_VENV) build *.egg-info
