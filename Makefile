# Quick start: `make demo` then `make test`. Both create or refresh .venv first.
VENV    ?= .venv
PY      := $(VENV)/bin/python
STAMP   := $(VENV)/.installed
DEMO    ?= demo_out

.PHONY: demo test test-fast lint api-docs bench bench-paper bench-beyond system-deps browser-deps clean

# Python may write its bytecode (and pytest its rewritten tests) where an environment says not to:
# without those caches every run compiles the library and the tests again.
unexport PYTHONDONTWRITEBYTECODE

# open3d and pyusb load the system's libusb-1.0 at import time; without it `import open3d` fails.
system-deps:
	@if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then \
	  echo "[make] libusb-1.0-0 is missing: open3d and pyusb need it to import. Installing it with apt-get."; \
	  if [ "$$(id -u)" = 0 ]; then apt-get update -qq && apt-get install -y -qq libusb-1.0-0 >/dev/null; \
	  else sudo apt-get update -qq && sudo apt-get install -y -qq libusb-1.0-0 >/dev/null; fi; \
	fi

$(STAMP): pyproject.toml constraints.txt
	@$(MAKE) --no-print-directory system-deps
	@test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -c constraints.txt -e '.[test]'
	@touch $(STAMP)

# The paper's regions and image size, from their one home (twinfocus.simulation.scenario; launch/paper.yaml
# holds the same for the launch files). Expanded only when a recipe uses it, after the venv exists.
PAPER_FOCUS_ARGS = $(shell $(PY) -c 'from twinfocus.simulation.scenario import PAPER_REFERENCE_ROI as r, PAPER_TARGET_ROI as t, \
	PAPER_IMAGE_SIZE as s; print("--reference-roi", *r, "--target-roi", *t, "--size", s)')

demo: $(STAMP)
	$(VENV)/bin/twinfocus simulate --overwrite --out $(DEMO)/scan.npz --template-out $(DEMO)/template_scan.npz
	$(VENV)/bin/twinfocus focus $(DEMO)/scan.npz --template-scan $(DEMO)/template_scan.npz \
	    $(PAPER_FOCUS_ARGS) --overwrite --out $(DEMO)/focus
	@$(PY) -m benchmarks.demo_figure $(DEMO)/focus
	@echo "[make] pictures and figures are in $(DEMO)/focus"

# The node-graph test opens the live web page in a real headless browser (Debian's chromium).
browser-deps:
	@if ! command -v chromium >/dev/null 2>&1; then \
	  echo "[make] chromium is missing: the visualizer's page test needs it. Installing it with apt-get."; \
	  if [ "$$(id -u)" = 0 ]; then apt-get update -qq && apt-get install -y -qq chromium >/dev/null; \
	  else sudo apt-get update -qq && sudo apt-get install -y -qq chromium >/dev/null; fi \
	  || echo "[make] could not install chromium: the browser test will be skipped"; \
	fi

# The whole suite on two pytest-xdist workers, one test file each at a time (a file's fixtures are
# built once): the tests wait on subprocesses, sockets and sleeps a good part of their time. Measured
# by benchmarks/bench_test_fast.py --all into benchmarks/results/test_suite.json, nothing else running
# on the machine: 908.9 s wall for 2440 tests (1752.7 s of summed test durations) at load 0.88 -> 2.09 on
# 2 cores. tests/test_makefile.py checks this comment against the file.
test: $(STAMP) browser-deps
	$(PY) -m pytest -q -n 2 --dist loadfile

# The tests not marked slow: the quick check while working (make test runs them all). Measured by
# benchmarks/bench_test_fast.py into benchmarks/results/test_fast.json, idle: 111.9 s wall for 2293 tests
# (99.5 s of summed test durations) at load 0.81 -> 1.12 on 2 cores. Rerun the script idle to refresh
# the file; tests/test_makefile.py checks this comment against it.
test-fast: $(STAMP)
	$(PY) -m pytest -q -m "not slow"

# Lint, types and the import layers (pyproject.toml's [tool.ruff], [tool.mypy], [tool.importlinter]).
# ruff covers the tests and the benchmarks as well as the library; mypy covers twinfocus, msgs and nodes.
LINT_DIRS = twinfocus msgs nodes tests benchmarks
lint: $(STAMP)
	$(VENV)/bin/ruff check $(LINT_DIRS)
	$(VENV)/bin/ruff format --check $(LINT_DIRS)
	$(VENV)/bin/mypy
	$(VENV)/bin/lint-imports

# The API reference, generated from the docstrings by pdoc into docs/api/ (not committed; open
# docs/api/index.html). tests/test_api_docs.py builds it the same way.
api-docs: $(STAMP)
	$(VENV)/bin/pdoc -o docs/api twinfocus msgs nodes
	@echo "[make] API reference: docs/api/index.html"

bench: $(STAMP)
	$(PY) -m benchmarks.run --out benchmarks/results

# The paper's evaluation in simulation at the paper's five error draws per pair, on two Dask workers
# (about 46 min on an idle 2-core machine: docs/performance.md, "Evaluation time"): docs/results.md +
# docs/results/. ARGS="--resume" keeps finished parts.
bench-paper: $(STAMP)
	nice $(VENV)/bin/twinfocus bench paper --draws 5 --workers 2 --out docs/results --markdown docs/results.md $(ARGS)

# Each improvement of the twin estimate beyond the paper, time against SSIM (about 18 min on 2 cores;
# the committed report is ARGS="--draws 2", about 30 min):
# docs/beyond.md + docs/beyond/.
bench-beyond: $(STAMP)
	nice $(VENV)/bin/twinfocus bench beyond --out docs/beyond --markdown docs/beyond.md $(ARGS)

clean:
	rm -rf $(VENV) $(DEMO) .pytest_cache
