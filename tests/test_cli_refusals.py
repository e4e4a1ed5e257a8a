"""Every override Hydra refuses is one line on stderr and exit 2, from every tool, as typed.

The real commands run as a user types them (subprocess, from the project root). Each refusal
comes before any simulator import, so each command costs its imports only (torch for
``march.train``, ``march.play`` and ``march.bench``: ~3 s; the others under 1 s). The line
says what is wrong and what is right: a group's options, the closest key, the type, where a
character is not allowed, how to write a list. ``HYDRA_FULL_ERROR=1`` still gives Hydra's
whole report.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent

BAD = {
    # override as typed: what its one line must hold
    "compute=smok": ("compute has no option 'smok'", "auto, cpu, gpu, smoke", "compute=smoke"),
    "student=ful": ("student has no option 'ful'", "full", "no_mdn"),
    "logger=tensorbord": ("logger has no option", "csv, tensorboard, wandb"),
    "rewards=clf": ("no key 'rewards'", "did you mean reward?"),
    "compute.num_envs=4.5": ("compute.num_envs=4.5", "Integer"),
    "seed=١٢": ("seed=١٢", "'١' (character 6)"),
    "reward=clf✓": ("reward=clf✓", "'✓' (character 11)"),
    "resume=x,y": ("resume=x,y", "-m", "resume=[...]"),
}
"""The eight overrides of issue 59, each Hydra's report of 5-12 lines and exit 1 before."""

TOOLS = {
    "train": ["-m", "march.train"],
    "inspect": ["-m", "march.inspect"],
    "inspect-list": ["-m", "march.inspect", "list"],
    "play": ["-m", "march.play"],
    "export": ["-m", "march.export"],
    "bench": ["-m", "march.bench", "env"],
    "audit": ["-m", "march.audit", "rewards"],
    "viz": ["-m", "march.viz", "terrain"],
}
"""Every ``python -m march.<tool>`` that takes Hydra overrides (``march.sim2sim`` and
``march.robot`` take their own ``key=value`` words, refused in one line by their parsers)."""

# march.train and march.inspect get all eight; every other tool one, each of another kind.
CASES = [(tool, ov) for tool in ("train", "inspect") for ov in BAD] + [
    (tool, list(BAD)[i % len(BAD)])
    for i, tool in enumerate(t for t in TOOLS if t not in ("train", "inspect"))
]


def run(tool: str, *args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, *TOOLS[tool], *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "PYTHONIOENCODING": "utf-8", **(env or {})},
    )


@pytest.mark.parametrize("tool, override", CASES, ids=[f"{t}:{o}" for t, o in CASES])
def test_a_refused_override_is_one_line_and_exit_2(tool, override):
    out = run(tool, override)
    lines = out.stderr.splitlines()
    assert out.returncode == 2 and len(lines) == 1, (out.returncode, out.stderr)
    for part in BAD[override]:
        assert part in lines[0], (part, lines[0])


def test_a_multirun_sweep_value_is_checked_too():
    out = run("train", "-m", "seed=0,1", "reward=clf,modelfre")
    assert out.returncode == 2 and len(out.stderr.splitlines()) == 1, out.stderr
    assert "reward has no option 'modelfre'" in out.stderr and "reward=modelfree" in out.stderr


@pytest.mark.parametrize("tool", ["train", "inspect"])
def test_hydra_full_error_gives_the_whole_report(tool):
    out = run(tool, "compute=smok", env={"HYDRA_FULL_ERROR": "1"})
    assert out.returncode != 0
    assert len(out.stderr.splitlines()) > 5 and "Traceback" in out.stderr, out.stderr
    assert "compute/smok" in out.stderr


def test_no_simulator_is_imported_before_the_refusal():
    """The refusal comes before mjlab (5+ s of imports) in the tool that composes the most."""
    code = (
        "import sys, runpy\n"
        "sys.argv = ['march.train', 'compute=smok']\n"
        "try:\n"
        "    runpy.run_module('march.train', run_name='__main__', alter_sys=True)\n"
        "except SystemExit as e:\n"
        "    print('mjlab' in sys.modules, e.code)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120
    )
    assert out.stdout.split() == ["False", "2"], (out.stdout, out.stderr)
