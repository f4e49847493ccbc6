# Two commands set up a fresh machine: `make demo` (the fleet demo) and `make test`.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
ROSLIBJS := tests/web/roslibjs/node_modules/.installed
FOXGLOVE_JS := tests/web/foxglove/node_modules/.installed

.PHONY: setup test demo bench bytecode system-deps clean

# Two distributions from this repository: rce (the engine, the root) and rce-fleet (examples/fleet), both editable.
$(STAMP): pyproject.toml examples/fleet/pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[test,ros2]' -e examples/fleet
	touch $(STAMP)

## setup: create .venv, install rce with its test extras and the Debian packages tests need (when root)
setup: $(STAMP) system-deps $(ROSLIBJS) $(FOXGLOVE_JS)

system-deps:
	@bash .ci/system-deps

# Unmodified roslibjs (npm roslib, pinned by package-lock.json) for the rosbridge browser test.
$(ROSLIBJS): tests/web/roslibjs/package.json tests/web/roslibjs/package-lock.json
	npm ci --prefix tests/web/roslibjs --no-audit --no-fund --silent
	touch $(ROSLIBJS)

# Foxglove's WebSocket protocol client and ROS 1 message libraries (npm, pinned by package-lock.json) for
# tests/web/test_foxglove.py.
$(FOXGLOVE_JS): tests/web/foxglove/package.json tests/web/foxglove/package-lock.json
	npm ci --prefix tests/web/foxglove --no-audit --no-fund --silent
	touch $(FOXGLOVE_JS)

## test: the whole suite, in parallel (tests share no ports, files or state; a test file runs in one worker),
## ending with its 15 slowest tests (the suite must stay under 10 minutes on a 2-core machine)
TEST_WORKERS ?= 4
test: setup bytecode
	$(BIN)/ruff check .
	env -u PYTHONDONTWRITEBYTECODE $(BIN)/python -m pytest -q -p no:cacheprovider -n $(TEST_WORKERS) --dist loadfile \
		--durations=15 $(PYTEST_ARGS)

## bytecode: compile the project's modules once, so that the hundreds of processes a run starts
## load them instead of compiling them each (PYTHONDONTWRITEBYTECODE keeps Python from caching them)
## (and, at the same time, the fleet's numba kernels into the tree's cache, which sandboxed fleet nodes load
## from instead of compiling them in every container: rce_fleet/numba_cache.py)
bytecode:
	@$(BIN)/python -m rce_fleet.compile_kernels & kernels=$$!; \
	$(BIN)/python -m compileall -q -j 0 rce rce_robot rce_master rce_container rce_client examples bench tests; \
	status=$$?; wait $$kernels && exit $$status

## demo: run the fleet demo (3 robots on the project's own map)
demo: setup bytecode
	$(BIN)/rce-fleet demo $(DEMO_ARGS)

## bench: all benchmarks, results in bench/results/
bench: setup
	$(BIN)/python bench/run_all.py

clean:
	rm -rf $(VENV) bench/results
