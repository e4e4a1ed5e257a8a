# march: one-command set-up. `make train` and `make test` create .venv if missing, install march
# with the CPU torch pin (constraints-cpu.txt) unless a GPU is present, then run.
VENV ?= .venv
PY := $(VENV)/bin/python
PYTHON ?= python3
ARGS ?=
export WARP_CACHE_PATH ?= $(CURDIR)/.warp_cache
export WANDB_MODE ?= offline

# On a machine with an NVIDIA driver let pip choose the CUDA torch build.
ifeq ($(shell command -v nvidia-smi 2>/dev/null),)
CONSTRAINTS := -c constraints-cpu.txt
else
CONSTRAINTS :=
endif

.PHONY: docs
.PHONY: install train smoke test test-all lint figures gpu-check test-slurm kill-trials two-node

# Byte code: pip would compile every module of every wheel, torch's thousands (74 s of the
# install here; 32 s with --no-compile). Instead Python writes the .pyc of what is imported, on
# first import, under .venv/pycache, also where the shell sets PYTHONDONTWRITEBYTECODE (it is
# set on this machine: without any .pyc every process of the test suite compiled its imports
# again, +7 min of CPU). The repository's own tree stays free of __pycache__.
export PYTHONDONTWRITEBYTECODE :=
export PYTHONPYCACHEPREFIX ?= $(CURDIR)/$(VENV)/pycache
$(VENV)/.installed: pyproject.toml constraints-cpu.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet --no-compile $(CONSTRAINTS) -e '.[dev,optuna,docs,camera]'
	touch $@

install: $(VENV)/.installed

# The main job on a CPU machine with 2 or more cores runs as 2 processes of one run (torchrun,
# gloo; march.learn.distributed): 2 x 16 envs step the cpu preset's 32 envs, one core each
# (mjlab's physics is ~93 % of a step and runs on one thread per process), gradients and the
# normalisers' moments are reduced over the two, the evaluations' 16 rollouts are dealt 8 + 8
# (their rows do not depend on the split: march.evaluation.sharding). Same iterations, env
# steps and rollouts as one process; different draws (rank 1 has its own seed stream), so
# its numbers are not one process's. TRAIN_RANKS=1 runs the single process (docs/decisions.md,
# issue 60). On a GPU machine, or with a compute choice in ARGS (another preset's envs): one.
ifeq ($(CONSTRAINTS),)
TRAIN_RANKS ?= 1
else ifneq ($(findstring compute,$(ARGS)),)
TRAIN_RANKS ?= 1
else
TRAIN_RANKS ?= $(shell n=$$(env -u OMP_NUM_THREADS -u OMP_THREAD_LIMIT nproc 2>/dev/null || echo 1); [ $$n -ge 2 ] && echo 2 || echo 1)
endif
ifeq ($(TRAIN_RANKS),2)
TRAIN_CMD := $(VENV)/bin/torchrun --standalone --nproc_per_node=2 -m march.train compute.num_envs=16 compute.eval_num_envs=8
else
TRAIN_CMD := $(PY) -m march.train
endif

train: $(VENV)/.installed  ## the main job: CLF teacher -> full student -> evaluation
	$(TRAIN_CMD) reward=clf student=full $(ARGS)

smoke: $(VENV)/.installed  ## the whole pipeline in a few minutes
	$(PY) -m march.train compute=smoke $(ARGS)

# One pytest-xdist worker per core, whole files to a worker (module fixtures build their env
# once); the session's smoke run and bundle are built once and shared (tests/conftest.py).
XDIST ?= -n auto --dist loadfile

test: $(VENV)/.installed  ## the test suite CI runs (slow extras left out)
	$(PY) -m pytest -q $(XDIST) $(ARGS)

# The documentation site (docs/, mkdocs.yml; Material theme) into site/: --strict makes a broken
# link, a missing page or a page left out of the navigation an error. The configuration
# reference, the tools' arguments and the decision records are generated from the code and
# docs/decisions.md while it builds (docs/hooks/march_docs.py). A link to a missing #anchor is an
# error too (mkdocs.yml: validation). No --quiet: mkdocs 1.6 drops warnings before the strict count
# then, so nothing failed (mkdocs issue 4126). ~10-25 s.
docs: $(VENV)/.installed  ## the documentation site: mkdocs build --strict -> site/
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict

# The robot loop on loopback DDS: the fault matrix (15 faults in up to 4 states, each in its own
# processes), the supervisor taking over from a killed policy, the camera through librealsense,
# the self-test, Unitree's bridge on damping alone (skipped without UNITREE_MUJOCO=, UNITREE_SDK2=
# and pygame); one process at a time (the matrix measures latencies). ~12 min on 2 cores.
robot-check: $(VENV)/.installed  ## the robot loop's fault matrix, supervisor, camera, self-test, Unitree's bridge on damping
	UNITREE_MUJOCO=$(UNITREE_MUJOCO) UNITREE_SDK2=$(UNITREE_SDK2) \
	$(PY) -m pytest -q -p no:xdist -s -m "" tests/test_robot_faults.py tests/test_robot_supervisor.py \
		tests/test_robot_camera.py tests/test_robot_checks.py tests/test_robot_loop.py \
		tests/test_robot_states.py tests/test_robot_hg.py tests/test_robot_unitree_bridge.py $(ARGS)

# march.robot policy against Unitree's own MuJoCo bridge (unitree_mujoco's simulate_python, run
# headless by march/robot/unitree_mujoco_run.py from your clone; nothing of it is copied), on
# loopback, robot=unitree_mujoco (its LowState: mode_machine 0, no CRC, tick 0; each command
# re-sent at its 200 Hz). Needs UNITREE_MUJOCO=<unitree_mujoco clone>, UNITREE_SDK2=<unitree_sdk2_python
# clone>, pygame installed, BUNDLE=<export folder>. Not in CI. docs/deploying.md has the outcome.
UNITREE_DOMAIN ?= 3
unitree-sim: $(VENV)/.installed  ## the robot loop against unitree_mujoco's bridge (UNITREE_MUJOCO= UNITREE_SDK2= BUNDLE=)
	@test -n "$(UNITREE_MUJOCO)" -a -n "$(UNITREE_SDK2)" -a -n "$(BUNDLE)" || \
		{ echo "give UNITREE_MUJOCO=<clone> UNITREE_SDK2=<clone> BUNDLE=<folder>"; exit 2; }
	PYTHONPATH=$(UNITREE_SDK2):$$PYTHONPATH $(PY) -m march.robot.unitree_mujoco_run \
		unitree_mujoco=$(UNITREE_MUJOCO) domain=$(UNITREE_DOMAIN) seconds=20 band_s=8 & sim=$$!; \
	sleep 3; $(PY) -m march.robot policy bundle=$(BUNDLE) domain=$(UNITREE_DOMAIN) interface=lo \
		robot=unitree_mujoco start=auto seconds=4 guard=report zero_torque_s=1 ramp_s=2 hold_s=1 \
		supervisor=none $(ARGS); rc=$$?; wait $$sim; simrc=$$?; \
		test $$simrc -eq 0 || echo "make unitree-sim: the bridge diverged or oscillated (exit $$simrc)"; \
		test $$rc -ne 0 && exit $$rc; exit $$simrc

test-all: $(VENV)/.installed  ## including tests marked slow
	$(PY) -m pytest -q -m "" $(XDIST) $(ARGS)

lint: $(VENV)/.installed
	$(VENV)/bin/ruff check march tests analysis scripts
	$(VENV)/bin/ruff format --check march tests analysis scripts

OUT ?= outputs/gpu_check
gpu-check: $(VENV)/.installed  ## the prepared GPU check into $(OUT) (ARGS=--cpu: tiny, on CPU)
	$(PY) scripts/gpu_check.py $(OUT) $(ARGS)

# A real single-node Slurm cluster on this machine (root; apt-installs slurm-wlm and munge if
# missing): a two-run smoke sweep through hydra/launcher=march_slurm, one job requeued mid-run
# with scontrol requeue (it must resume from its checkpoint), analysis/figures.py on the sweep.
# Slow (~5-10 min on 2 CPUs) and not in CI. Prints PASSED/FAILED with one line per check.
test-slurm: $(VENV)/.installed
	scripts/slurm/test.sh $(ARGS)

# Kill-and-resume trials: SIGKILL a small smoke run at seeded random moments (teacher, checkpoint
# writes, distillation, final evaluation), resume it, check every row and checkpoint. Prints the
# tally; ~3-5 min per trial on 2 CPUs. ARGS="--trials 3 --seed 1" for fewer or other moments.
kill-trials: $(VENV)/.installed
	$(PY) scripts/kill_trials.py $(ARGS)

# Two nodes on one machine: two torchrun processes (--nnodes=2 --node_rank=0|1, c10d rendezvous on
# 127.0.0.1) train one smoke run together, in the usual order and with the node ranks swapped
# (global rank 0 on --node_rank=1); checks one run directory that follows global rank 0 and
# weights equal on both nodes after every PPO and distillation update (docs/scaling.md).
# ~2-4 min on 2 CPUs; ARGS="--order swapped" for one order.
two-node: $(VENV)/.installed
	$(PY) scripts/two_node.py $(ARGS)
