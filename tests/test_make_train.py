"""``make train``'s launch (issue 60): on a CPU machine with 2 or more cores, two torchrun ranks
of 16 envs (the cpu preset's 32) and 8 evaluation envs each; one process with ``TRAIN_RANKS=1``,
with a ``compute=`` choice in ``ARGS`` (another preset's envs) or on one core. Read from
``make -n`` (what make would run), nothing is trained."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CORES = len(os.sched_getaffinity(0))
GPU = shutil.which("nvidia-smi") is not None


# What the suite's own make line set must not reach this make: make hands a command-line
# variable (``make test ARGS=...``) to its recipes' environment as well as to MAKEFLAGS.
MAKE_ENV = {
    k: v
    for k, v in os.environ.items()
    if k not in ("ARGS", "TRAIN_RANKS", "MAKEFLAGS", "MFLAGS", "MAKELEVEL")
}


def recipe(*args: str) -> str:
    """The command ``make train`` would run (its last line), with ``args`` on make's line."""
    out = subprocess.run(
        ["make", "-n", "-s", "-C", str(ROOT), "train", *args],
        capture_output=True,
        text=True,
        check=True,
        env=MAKE_ENV,
    ).stdout
    return out.strip().splitlines()[-1]


@pytest.mark.skipif(GPU, reason="a GPU machine trains in one process")
def test_a_multicore_cpu_trains_over_two_ranks_of_the_cpu_presets_envs():
    line = recipe()
    if CORES < 2:
        assert "torchrun" not in line, line
        return
    assert "torchrun --standalone --nproc_per_node=2 -m march.train" in line, line
    words = line.split()
    assert "compute.num_envs=16" in words and "compute.eval_num_envs=8" in words, line
    assert words[-2:] == ["reward=clf", "student=full"], line
    # ARGS come last, so a resume or a seed rides along with the two ranks
    assert recipe("ARGS=seed=3").split()[-1] == "seed=3"


@pytest.mark.parametrize("args", [["TRAIN_RANKS=1"], ["ARGS=compute=smoke"], ["ARGS=compute=cpu"]])
def test_one_process_when_asked_or_with_another_preset(args):
    line = recipe(*args)
    assert "torchrun" not in line and "compute.num_envs=16" not in line, line
    assert " -m march.train reward=clf student=full" in line, line
