# The two entry points of the README: `make demo` and `make test`. Both set everything up first.
SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python
export MUJOCO_GL ?= egl
export PYOPENGL_PLATFORM ?= egl
export HF_HUB_OFFLINE ?= 1
export TOKENIZERS_PARALLELISM ?= false

.PHONY: setup demo test test-fast bench experiments weak-expert lab-loop clean

setup:
	@bash scripts/setup.sh

demo: setup
	@bash scripts/demo.sh

experiments: setup   # make experiments SIGMA=0.01 [MODE=images]: the paper's runs for one sigma (docs/RESULTS.md)
	SIGMA=$(or $(SIGMA),0.1) MODE=$(or $(MODE),lowdim) bash scripts/experiments.sh

weak-expert: setup   # the paper's kind of demonstrator, a weak learned policy (configs/record_weak_expert.yaml)
	bash scripts/weak_expert.sh

lab-loop: setup   # demos through the real robot's command path -> bags -> dataset -> image BC -> run back through it
	URDF=$(or $(URDF),../shared/robots/sawyer/sawyer.urdf) bash scripts/lab_loop.sh

test: setup
	$(PY) -m pytest -q --durations=25 tests

test-fast: setup
	$(PY) -m pytest -q -m "not slow" tests

bench: setup
	$(PY) bench/env_throughput.py
	OMP_NUM_THREADS=1 $(PY) bench/rollout_throughput.py
	OMP_NUM_THREADS=1 $(PY) bench/rollout_throughput.py --ray_cluster
	OMP_NUM_THREADS=1 $(PY) bench/worker_memory.py
	@echo "BC and image BC+RL learner throughput need a camera dataset: $(PY) bench/bc_throughput.py --root=<bcrl-record dataset>, OMP_NUM_THREADS=1 $(PY) bench/learner_throughput.py --root=<the same> --threads=2; conversion: $(PY) bench/convert_speed.py"

clean:
	rm -rf outputs .pytest_cache
