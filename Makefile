# ddsgen: `make demo` installs and renders a demo dataset; `make test` installs and runs the tests.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
DDSGEN := $(VENV)/bin/ddsgen
WORKERS ?= 2

# Dataset build parameters: make dataset PRESET=presets/kinect_v1.yaml SCENES=scenes/default.yaml N=100 OUT=datasets/kv1
PRESET ?= presets/kinect_v1.yaml
SCENES ?=
N ?= 100
OUT ?= datasets/$(basename $(notdir $(PRESET)))
SEED ?= 0
FORMAT ?= ddsgen

.PHONY: install demo test bench dataset datasets clean

install: $(VENV)/.installed

# torch==2.13.0 first: it is the CPU wheel; an unpinned torch would pull a multi-GB CUDA build.
$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e ".[test,dask]"
	touch $@

demo: install
	$(DDSGEN) render presets/kinect_v1.yaml -n 12 --out demo_out --workers $(WORKERS) --seed 0
	@echo "demo dataset: demo_out/ (open demo_out/manifest.jsonl, depth/*.png, ir/*.png)"

test: install
	$(PY) -m pytest -q -p no:cacheprovider

bench: install
	$(PY) bench/run_all.py

dataset: install
	$(DDSGEN) render $(PRESET) $(if $(SCENES),--scenes $(SCENES)) -n $(N) --out $(OUT) --workers $(WORKERS) --seed $(SEED) $(if $(filter bop,$(FORMAT)),--format bop)

datasets: install
	$(MAKE) dataset PRESET=presets/kinect_v1.yaml SCENES=scenes/default.yaml N=$(N) OUT=datasets/kinect_v1
	$(MAKE) dataset PRESET=presets/matterport_pro2.yaml SCENES=scenes/default.yaml N=$(N) OUT=datasets/matterport_pro2

clean:
	rm -rf demo_out datasets .pytest_cache .hypothesis build *.egg-info
