# pinnmpc: every user-facing task. Hydra overrides go after the target, e.g. `make closed-loop animate=true`
# or `make train seed=1` (or in ARGS="..."); the make variables below are not passed on.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
TORCH_SPEC ?= torch==2.13.0
TORCH_PIP_ARGS ?=
ARGS ?=
SHARED_REF ?= ../shared/powercube/reference
CPU_RUNS ?=
# Every `name=value` given to make becomes one Hydra override, in command-line order, each exactly once and
# shell-quoted as one argument (values may hold spaces); ARGS="a=1 b=2" is split by the shell like a command line.
KNOBS := ARGS PYTHON VENV TORCH_SPEC TORCH_PIP_ARGS SHARED_REF CPU_RUNS
space := $(subst ,, )
reverse = $(if $(1),$(call reverse,$(wordlist 2,$(words $(1)),$(1))) $(firstword $(1)))
uniq = $(if $(1),$(firstword $(1)) $(call uniq,$(filter-out $(firstword $(1)),$(1))))
# MAKEOVERRIDES lists them last-first, with a value's spaces escaped as "\ ": keep only each name
CLI_NAMES := $(call uniq,$(call reverse,$(foreach d,$(subst \$(space),^,$(MAKEOVERRIDES)),$(firstword $(subst =, ,$(d))))))
shell_quote = '$(subst ','\'',$(1))'
OVERRIDES = $(foreach v,$(filter-out $(KNOBS),$(CLI_NAMES)),$(call shell_quote,$(v)=$($(v)))) $(ARGS)

.PHONY: install train gpu-curves collect identify self-loop residuals time-basis capacity closed-loop closed-loop-paper robustness evaluate bench sweep sweep-optuna tensorboard test test-all lint format contract clean

install: $(VENV)/.installed  ## venv with a CPU build of torch, the package (editable) and its extras

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet "$(TORCH_SPEC)" $(TORCH_PIP_ARGS)
	$(PY) -m pip install --quiet -e ".[dev,sweep,franka]"
	touch $@

train: install  ## train the default PINN (under 30 min on 2 cores); outputs/train/<time>/
	$(PY) -m pinnmpc.train $(OVERRIDES)

GPU_RUN = $(PY) -m pinnmpc.train progress=false self_loop_figure.every_n_epochs=0
gpu-curves: install  ## on one GPU: PowerCube default 1.5 min, Panda recipes 3.3 min each; RMSE vs minutes (+ CPU_RUNS="dir=label ...")
	d=outputs/gpu-curves/$$(date +%Y-%m-%d_%H-%M-%S) && \
	$(GPU_RUN) trainer=gpu threads=0 trainer.max_time=00:00:01:30 hydra.run.dir=$$d/powercube $(OVERRIDES) && \
	$(GPU_RUN) experiment=panda-frozen trainer=gpu threads=0 trainer.max_time=00:00:03:20 hydra.run.dir=$$d/panda $(OVERRIDES) && \
	$(GPU_RUN) experiment=panda-gpu trainer.max_time=00:00:03:20 hydra.run.dir=$$d/panda-gpu $(OVERRIDES) && \
	$(PY) -m pinnmpc.curves $$d/powercube="PowerCube, GPU" $$d/panda="Panda (frozen_arm), GPU" \
		$$d/panda-gpu="Panda (frozen_arm), GPU, 4x points" $(CPU_RUNS) --out $$d/curves.png

self-loop: install  ## the paper's 20-step self-loop test with the shipped checkpoint
	$(PY) -m pinnmpc.self_loop $(OVERRIDES)

residuals: install  ## where the shipped network breaks the physics: ODE residual by state and time in the step
	$(PY) -m pinnmpc.residuals $(OVERRIDES)

time-basis: install  ## can the time gates span the flow? misfit per state, and the relaxation times that help
	$(PY) -m pinnmpc.time_basis $(OVERRIDES)

capacity: install  ## can the network represent the one-step map? a direct fit to true steps, against the targets
	$(PY) -m pinnmpc.capacity $(OVERRIDES)

closed-loop: install  ## NMPC tracks the built-in reference on the RK45 plant (the main job)
	$(PY) -m pinnmpc.closed_loop $(OVERRIDES)

closed-loop-paper: install  ## the paper's reference from ../shared (paper settings are the defaults)
	$(PY) -m pinnmpc.closed_loop reference.path=$(SHARED_REF) $(OVERRIDES)

collect: install  ## run the (simulated) robot for robot_time s and write its log (outputs/collect/<time>/)
	$(PY) -m pinnmpc.collect $(OVERRIDES)

identify: install  ## fit the model's friction, payload and armature to robot logs; a system .yaml (logs=[...] out=...)
	$(PY) -m pinnmpc.identify $(OVERRIDES)

.PHONY: export
export: install  ## the flow map and its Jacobian for CasADi, C or ONNX (format=casadi|c|onnx out=DIR), checked vs torch
	$(PY) -m pinnmpc.export $(OVERRIDES)

robustness: install  ## closed loops under measurement noise and friction/mass mismatch, one table
	$(PY) -m pinnmpc.robustness $(OVERRIDES)

evaluate: install  ## one-step accuracy and cost of the surrogate vs Euler/RK4/RK45 (the bench's step table only)
	$(PY) -m pinnmpc.bench closed_loop.enabled=false optimality.enabled=false scaling.enabled=false \
	  kinds.enabled=false floor.enabled=false peers.enabled=false $(OVERRIDES)

bench: install  ## benchmarks: bench.json, bench.md and plots in outputs/bench/<time>/
	$(PY) -m pinnmpc.bench $(OVERRIDES)

sweep: install  ## local grid search in parallel (joblib launcher); table in the sweep dir
	$(PY) -m pinnmpc.train -m hparams_search=grid $(OVERRIDES)

sweep-optuna: install  ## Optuna search minimising the validation RMSE
	$(PY) -m pinnmpc.train -m hparams_search=optuna $(OVERRIDES)

tensorboard: install  ## TensorBoard over every run in outputs/
	$(VENV)/bin/tensorboard --logdir outputs

test: install  ## the default test run (a few minutes)
	$(PY) -m pytest -m "not slow" -q -n auto --dist worksteal  # worksteal: no core idles while the other ends a long test

test-all: install  ## every test, the slow ones too
	$(PY) -m pytest -q -n auto --dist worksteal

lint: install
	$(VENV)/bin/ruff check pinnmpc tests
	$(VENV)/bin/ruff format --check pinnmpc tests

format: install
	$(VENV)/bin/ruff format pinnmpc tests
	$(VENV)/bin/ruff check --fix pinnmpc tests

contract: install  ## the outside contract checks in ../shared
	$(PY) ../shared/tools/check_contract.py --closed-loop --arms --casadi

clean:  ## delete outputs/ (sweeps too: outputs/train_multirun/) and caches; keeps run dirs of live runs and shipped checkpoints
	$(PY) -m pinnmpc.cli clean outputs multirun lightning_logs
	rm -rf .pytest_cache .ruff_cache
