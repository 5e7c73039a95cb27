PY ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# exact versions of every direct and transitive dependency (pip-compile; `make lock` refreshes it)
LOCK := requirements.lock
PIP_VERSION := 26.3
# the build backend test-lab's editable install uses (--no-build-isolation): a fresh venv
# has Python 3.11's bundled setuptools 65.5, which needs the separate `wheel` package for
# an editable install ("invalid command 'bdist_wheel'"); 70.1 and later build wheels alone
SETUPTOOLS_VERSION := 80.9.0
PYTEST_ARGS = -q -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder
# The tests and the demo keep compiled bytecode (__pycache__, git-ignored) even where the
# environment says not to (PYTHONDONTWRITEBYTECODE, set on this machine; empty counts as
# unset): without it every pytest process rewrote and compiled all test modules anew
# (collection 17.6 → 5.5 s of CPU per worker) and every `feedbench` subprocess of the tests
# compiled feedbench again. (Python's own rule then holds: a file edited to the same size
# within the second of its last compile runs stale until touched.)
demo test test-fast test-lab test-latest: export PYTHONDONTWRITEBYTECODE :=

.PHONY: demo test test-lab test-fast test-latest lock bench bench-suite docs clean

# the stamp holds the set-up's wall time (s), which `make demo` reports
$(STAMP): pyproject.toml $(LOCK)
	start=$$(date +%s) && \
	$(PY) -m venv $(VENV) && \
	$(BIN)/pip install --quiet 'pip==$(PIP_VERSION)' && \
	$(BIN)/pip install --quiet -c $(LOCK) -e '.[test]' && \
	echo $$(( $$(date +%s) - start )) > $(STAMP)

$(VENV)/.bench: $(STAMP)
	$(BIN)/pip install --quiet -c $(LOCK) -e '.[test,bench]'
	touch $(VENV)/.bench

# the demo prints where its time went; then the set-up of this clone (once, before it)
demo: $(STAMP)
	$(BIN)/feedbench demo --quick
	@s=$$(cat $(STAMP)); echo "Set-up of this clone (venv + pip install, once):" \
		"$${s:-not timed}$${s:+ s}; the first demo also compiles the physics (numba, cached)"

# two xdist workers, whole files each, slowest files first (tests/conftest.py): 1450 tests
# in 5 min 38–53 s on this 2-core machine, quiet (30 Nov; all of `make test` 5 min 58 s
# to 6 min 25 s, 7 min 50 s beside a process burning one CPU; `make bench-suite` times it)
# then the real-time tests alone (marked realtime): a host loop starved by the other
# worker's CPU is what they measure against, not what they may run beside; only the files
# that mark a test realtime are collected for them (collecting the whole suite to deselect
# all but those took 10-25 s; no such file: the whole suite, as before)
TEST_WORKERS ?= 2
REALTIME_FILES = $(shell grep -l 'mark\.realtime' tests/test_*.py)
test: $(STAMP)
	QT_QPA_PLATFORM=offscreen $(BIN)/python -m pytest $(PYTEST_ARGS) -m "not realtime"
	QT_QPA_PLATFORM=offscreen $(BIN)/python -m pytest -q -n 0 -m realtime $(REALTIME_FILES)
	$(MAKE) test-lab

# the worked example of a lab's extension (examples/lab_extension: its own package, entry
# points in its own pyproject.toml) installed beside feedbench, where it stays: its tests
# (run, analyze, report, sim, demo, campaign), then feedbench's tests of what is registered
LAB_TESTS := tests/test_bench_tables.py tests/test_testing_kit.py tests/test_device_seam.py \
	tests/test_sim_serves_all.py::test_the_docs_list_both_modbus_devices_and_the_sims_serve_them
# (installed once per venv, again when its pyproject.toml, its entry points, or this file,
# SETUPTOOLS_VERSION, changes: the install is editable, its code is read where it is; 5 s
# a suite saved)
LAB_STAMP := $(VENV)/.lab-extension
$(LAB_STAMP): $(STAMP) examples/lab_extension/pyproject.toml Makefile
	$(BIN)/pip install --quiet 'setuptools==$(SETUPTOOLS_VERSION)'
	$(BIN)/pip install --quiet --no-deps --no-build-isolation -e examples/lab_extension
	touch $(LAB_STAMP)

# (the two at once, one a core, each one's output whole: 8 s instead of 14 s; each its own
# numba cache, as each test worker has: two processes compiling one kernel into one cache
# directory can corrupt its index, tests/conftest.py)
LAB_NUMBA = NUMBA_CACHE_DIR=$(abspath .pytest_cache/numba)/$@
test-lab: $(LAB_STAMP)
	$(MAKE) -j2 $(if $(filter output-sync,$(.FEATURES)),--output-sync=target) \
		lab-extension-tests lab-registered-tests

.PHONY: lab-extension-tests lab-registered-tests
lab-extension-tests: $(LAB_STAMP)
	cd examples/lab_extension && QT_QPA_PLATFORM=offscreen $(LAB_NUMBA) \
		$(abspath $(BIN))/python -m pytest -q -p no:cacheprovider

lab-registered-tests: $(LAB_STAMP)
	QT_QPA_PLATFORM=offscreen $(LAB_NUMBA) $(BIN)/python -m pytest -q -n 0 $(LAB_TESTS)

# the edit loop: the suite without the files marked slow (tests/conftest.py: SLOW_FIRST,
# each 5 s or more alone), under a minute on 2 workers
test-fast: $(STAMP)
	QT_QPA_PLATFORM=offscreen $(BIN)/python -m pytest $(PYTEST_ARGS) -m "not slow and not realtime"

# the suite with the newest versions pyproject.toml allows (no lock), in its own fresh
# environment: shows dependency drift before a fresh machine's user meets it
test-latest:
	rm -rf .venv-latest
	$(PY) -m venv .venv-latest
	.venv-latest/bin/pip install --quiet --upgrade pip
	.venv-latest/bin/pip install --quiet --upgrade -e '.[test]'
	QT_QPA_PLATFORM=offscreen NUMBA_CACHE_DIR=.venv-latest/numba \
		.venv-latest/bin/python -m pytest $(PYTEST_ARGS) -p no:cacheprovider -m "not realtime"
	QT_QPA_PLATFORM=offscreen NUMBA_CACHE_DIR=.venv-latest/numba \
		.venv-latest/bin/python -m pytest -q -n 0 -p no:cacheprovider -m realtime

# re-resolve the newest versions within pyproject.toml's ranges into the lock file
lock: $(STAMP)
	$(BIN)/pip install --quiet 'pip-tools>=7.4'
	$(BIN)/pip-compile --quiet --upgrade --extra test --extra bench --strip-extras \
		--no-emit-index-url --no-emit-find-links -o $(LOCK) pyproject.toml

# the API reference (Sphinx autodoc of feedbench.api), warnings as errors, no network
docs: $(STAMP)
	$(BIN)/sphinx-build -W -q -b html docs/api docs/_build/html
	@echo "docs/_build/html/index.html"

bench: $(VENV)/.bench
	QT_QPA_PLATFORM=offscreen $(BIN)/python benchmarks/run_all.py

# `make test` timed whole, quiet and beside a process burning one CPU (≈ 15 min; `make
# bench` leaves it out unless FEEDBENCH_BENCH_SUITE=1)
bench-suite: $(VENV)/.bench
	FEEDBENCH_BENCH_SUITE=1 $(BIN)/python benchmarks/run_all.py suite

clean:
	rm -rf $(VENV) .venv-latest runs .pytest_cache
