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
# Optional: SCHEDULER=tcp://HOST:PORT renders on a Dask cluster (workers: dask worker ADDR --nworkers K --nthreads 1);
# BATCH=frames per task.
SCHEDULER ?=
BATCH ?= 1

.PHONY: install demo test bench dataset datasets clean

install: $(VENV)/.installed

# torch==2.13.0 first: on the project's machines pip finds its CPU wheel; an unpinned torch would pull a multi-GB
# CUDA build. Where pip's index is plain PyPI (whose Linux torch is the CUDA build), take PyTorch's CPU index:
#   make demo TORCH_PIP_ARGS="--index-url https://download.pytorch.org/whl/cpu"
TORCH_PIP_ARGS ?=
$(VENV)/.installed: pyproject.toml setup.py
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0 $(TORCH_PIP_ARGS)
	$(PY) -m pip install -q -e ".[test,dask]"
	touch $@

demo: install
	$(DDSGEN) render presets/kinect_v1.yaml -n 12 --out demo_out --workers $(WORKERS) --seed 0
	@echo "demo dataset: demo_out/ (look at demo_out/preview.png; files: manifest.jsonl, depth/*.png, ir/*.png)"

# Two pytest workers: the slow tests (diagnose, fit) run one torch thread each. worksteal: the last slow tests
# queued on one worker are taken by the idle one (with the default 'load' one core idled ~15 min at the end).
test: install
	$(PY) -m pytest -q -p no:cacheprovider -n 2 --dist worksteal

bench: install
	$(PY) bench/run_all.py

# Re-running the same command resumes an interrupted build (finished frames are kept).
dataset: install
	$(DDSGEN) render $(PRESET) $(if $(SCENES),--scenes $(SCENES)) -n $(N) --out $(OUT) --workers $(WORKERS) \
		--seed $(SEED) --format $(FORMAT) --batch-size $(BATCH) $(if $(SCHEDULER),--scheduler $(SCHEDULER))

# A kinect_v1 and a matterport_pro2 dataset from the shipped scene list (FORMAT=bop for the BOP layout).
datasets: install
	$(MAKE) dataset PRESET=presets/kinect_v1.yaml SCENES=scenes/default.yaml N=$(N) OUT=datasets/kinect_v1$(if $(filter bop,$(FORMAT)),_bop)
	$(MAKE) dataset PRESET=presets/matterport_pro2.yaml SCENES=scenes/default.yaml N=$(N) OUT=datasets/matterport_pro2$(if $(filter bop,$(FORMAT)),_bop)

clean:
	rm -rf demo_out datasets .pytest_cache .hypothesis build *.egg-info
