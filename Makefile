# The two commands a new user needs: `make demo` and `make test`. Both set everything up first.
# `make help` lists every target; `make bench-gpu` is the GPU benchmark suite (needs a CUDA device).
.PHONY: help setup demo test lint bench bench-gpu viewer clean

VENV := .venv
STAMP := $(VENV)/.bootstrapped

setup: $(STAMP)

# Recipes are not echoed: bootstrap.sh and demo.sh print their own [bootstrap] / [demo] progress (what pip and
# apt-get print goes to .venv/bootstrap.log).
$(STAMP): pyproject.toml scripts/bootstrap.sh
	@bash scripts/bootstrap.sh
	@touch $(STAMP)

demo: $(STAMP)
	@VENV=$(VENV) bash scripts/demo.sh

# Two pytest workers (pytest-xdist), each running whole test files in file order (`--dist loadfile`: many files
# share a module-scoped server or session that their tests build on, so a file is never split), each worker's torch
# on its share of the cores (tests/conftest.py): 4:53 of tests on the 2-core AMD EPYC, against 10:23 in the same hour
# with two torch threads per worker (2026-11-28).
test: $(STAMP)
	$(VENV)/bin/python -m pytest -q -n 2 --dist loadfile

lint: $(STAMP)
	$(VENV)/bin/ruff check .

# GPU benchmark suite (bench/gpu_suite.py): ms per tracking / mapping iteration at the paper preset, realtime
# session rates at 30 Hz, render latency, mesh time, peak GPU memory, concurrent sessions per GPU; writes
# bench/results/gpu-<gpu>.json. Refuses with a message when no CUDA device is visible.
bench-gpu: $(STAMP)
	$(VENV)/bin/python bench/gpu_suite.py

# The live web viewer (server/viewer: three.js bundled by vite). Its build, server/viewer/dist, is committed so the
# server needs no Node.js; rebuild it after changing the viewer's sources (needs Node.js >= 20.19 and npm).
viewer: $(STAMP)
	@cd server/viewer && npm ci --no-audit --no-fund --loglevel=error >/dev/null && npx vite build --logLevel warn
	@$(VENV)/bin/python -c 'from voxfusion.server.viewer_assets import write_build_info as w; print("[viewer] built; wrote", w())'

help:
	@echo "make demo       set up, start the server, stream a synthetic capture, print ATE and fps"
	@echo "make test       set up, run the test suite (CPU only)"
	@echo "make lint       ruff check ."
	@echo "make bench-gpu  GPU benchmark suite -> bench/results/gpu-<gpu>.json (needs CUDA; up to ~20 min)"
	@echo "make viewer     rebuild the live web viewer (server/viewer/dist; needs Node.js and npm)"
	@echo "make setup      create .venv and install everything (the other targets do it first)"
	@echo "make clean      remove .venv and build files"

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info
