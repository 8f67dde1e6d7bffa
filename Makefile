# Two-command quick start: `make demo` and `make test`. Only Python 3.11+ and make are needed.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: demo test test-gpu bench venv clean

$(STAMP): pyproject.toml
	@$(PYTHON) -c 'import sys; assert sys.version_info >= (3, 11), "orbitct needs Python 3.11 or newer, found " + sys.version.split()[0]'
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	@echo "compiling the numerical kernels once (cached; the first calibration and reconstruction then start at full speed)"
	$(BIN)/orbitct warmup
	$(BIN)/python -m orbitct_app.console.assets
	@touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(BIN)/orbitct demo --out demo-output

# Two test processes (one per core of the target machines); a file's tests stay in one process (their fixtures).
TEST_WORKERS ?= 2
# More pytest options (.ci/run adds coverage).
PYTEST_ARGS ?=

test: $(STAMP)
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile $(PYTEST_ARGS)

# The GPU suite (tests marked gpu, left out of `make test`) on this machine's GPU, with the gpu extra.
test-gpu: $(STAMP)
	$(BIN)/python -m pip install --quiet -e '.[test,gpu]'
	NUMBA_ENABLE_CUDASIM=0 $(BIN)/python -m pytest -q --gpu $(PYTEST_ARGS)

bench: $(STAMP)
	$(BIN)/python benchmarks/record.py --quick

clean:
	rm -rf $(VENV) demo-output .pytest_cache
