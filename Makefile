# dars — make help lists the targets. Every target does its own set-up (apt packages if missing, .venv, pip).
SHELL := /bin/bash
VENV  := .venv
PY    := $(VENV)/bin/python
DARS  := $(VENV)/bin/dars
SAMPLE ?= samples/gallery
OUT   ?= demo_out
export DRJIT_LIBLLVM_PATH ?= /usr/lib/x86_64-linux-gnu/libLLVM.so.19.1
export OMP_NUM_THREADS ?= 2

.PHONY: help install demo test test-fast bench sample clean

help:  ## list the targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | awk 'BEGIN{FS=":.*## "}{printf "  make %-10s %s\n", $$1, $$2}'

install:  ## set up .venv (apt packages if missing, pinned CPU torch stack, the `dars` command)
	@bash scripts/setup.sh

demo: install  ## run the main job on the bundled sample (writes $(OUT)/)
	@bash scripts/demo.sh $(SAMPLE) $(OUT)

test: install  ## run the whole test suite
	$(PY) -m pytest tests

test-fast: install  ## the suite without tests marked slow
	$(PY) -m pytest tests -m "not slow"

bench: install  ## run the benchmarks in bench/ (prints figures and ratios)
	@for b in bench/bench_*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

sample: install  ## re-render the bundled sample scene with Mitsuba 3 (overwrites samples/gallery)
	$(PY) samples/render_gallery.py --preset sample --out $(SAMPLE)

clean:  ## remove demo outputs and caches (keeps .venv)
	rm -rf $(OUT) .pytest_cache
