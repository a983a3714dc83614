# mocapskel: `make demo` fits the sample takes, `make test` runs the tests,
# `make bench` measures speed and accuracy into BENCHMARKS.md.
# Each target makes its own virtual environment (.venv) and installs what it needs.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
DEMO_CACHE := out/.cache

.PHONY: venv demo test bench clean-out sample-data

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[test]'
	touch $(STAMP)

venv: $(STAMP)

demo: venv
	mkdir -p out
	$(BIN)/mocapskel fit sample_data/human_rom.c3d -o out/human_rom.bvh --report out/human_rom.json --cache-dir $(DEMO_CACHE)
	$(BIN)/mocapskel fit sample_data/linkage.trc -o out/linkage.bvh --report out/linkage.json --cache-dir $(DEMO_CACHE)
	$(BIN)/mocapskel inspect out/human_rom.bvh
	@echo "demo: BVH and reports written to out/"

test: venv
	$(BIN)/python -m pytest -q -p no:cacheprovider -n 2 --dist loadfile

bench: venv
	$(BIN)/python -m bench.run_all

sample-data: venv
	$(BIN)/python -m bench.make_sample_data

clean-out:
	rm -rf out
