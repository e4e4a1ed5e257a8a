"""Plug-in modules from the command line (issue 36, item 4): a fresh process, a module outside
the repository (on PYTHONPATH only) and an arm YAML on ``hydra.searchpath``, nothing registered
in-process. ``extra_modules=[my_terms]`` is imported before the config is checked: the arm's term
runs with the parameter its YAML sets, ``march.inspect list`` lists it, and without the module the
arm is refused in one line that says how to fix it."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

ROOT = Path(__file__).resolve().parent.parent
pytestmark = pytest.mark.sim

MODULE = '''\
"""An out-of-tree reward term: swing-foot clearance above the ground."""
import os

import torch

from march.env.rewards import reward_term


@reward_term("swing_clearance", height=0.05)
def swing_clearance(env, height: float) -> torch.Tensor:
    """min(swing foot height, height) / height, the swing foot being the higher of the two foot
    sites (height above the env's origin): 1 once it clears ``height`` [m]."""
    log = os.environ.get("MY_TERMS_LOG")
    if log and not os.path.exists(log):  # the first call says which height it got
        with open(log, "w") as f:
            f.write(repr(height))
    robot = env.scene["robot"]
    ids, _ = robot.find_sites(("left_foot", "right_foot"), preserve_order=True)
    z = robot.data.site_pos_w[:, ids, 2].max(dim=1).values - env.scene.env_origins[:, 2]
    return torch.clamp(z, max=height) / height
'''

ARM = """\
name: my_arm
label: model-free + swing clearance
terms:
  track_linear_velocity: 2.0
  alive: 0.5
  torque: 1.0e-5
  action_rate: 0.01
  swing_clearance: {weight: 0.5, params: {height: 0.123}}
"""

SWEEP = """\
figures:
  compare: ["my_arm:modelfree"]
extra_modules: [my_terms]
hydra:
  sweeper:
    params:
      reward: modelfree,my_arm
"""

QUICK = [
    "stage=teacher",
    "teacher.max_iterations=2",
    "env.episode_length_s=0.1",
    "eval.num_rollouts=2",
    "eval.episode_length_s=0.3",
]


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    root = tmp_path_factory.mktemp("my_lab")
    (root / "my_terms.py").write_text(MODULE)
    (root / "my_conf" / "reward").mkdir(parents=True)
    (root / "my_conf" / "reward" / "my_arm.yaml").write_text(ARM)
    (root / "my_conf" / "sweep").mkdir()
    (root / "my_conf" / "sweep" / "my_sweep.yaml").write_text(SWEEP)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env |= {"PYTHONPATH": str(root), "MY_TERMS_LOG": str(root / "height.txt")}
    env.setdefault("WANDB_MODE", "offline")
    search = f"hydra.searchpath=[file://{root / 'my_conf'}]"
    return {"root": root, "env": env, "search": search}


def _run(lab, module: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", module, *args],
        cwd=lab["root"],  # outside the repository: a user's own directory
        env=lab["env"],
        capture_output=True,
        text=True,
        timeout=900,
    )


def test_without_the_module_the_arm_is_one_line(lab):
    res = _run(lab, "march.train", "compute=smoke", lab["search"], "reward=my_arm", *QUICK)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.returncode == 2 and len(lines) == 1, res.stderr[-3000:]
    assert "unknown reward term(s) ['swing_clearance']" in lines[0]
    assert "extra_modules=[...]" in lines[0]
    res = _run(lab, "march.train", "compute=smoke", "extra_modules=[no_such_lab]", *QUICK)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.returncode == 2 and len(lines) == 1 and "cannot import 'no_such_lab'" in lines[0]


def test_train_runs_the_plugin_term_with_its_yaml_parameter(lab):
    run = lab["root"] / "run"
    res = _run(
        lab,
        "march.train",
        "compute=smoke",
        "extra_modules=[my_terms]",
        lab["search"],
        "reward=my_arm",
        f"hydra.run.dir={run}",
        *QUICK,
    )
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    assert (lab["root"] / "height.txt").read_text() == "0.123"  # the YAML's, not the default
    assert json.loads((run / "status.json").read_text())["state"] == "done"
    saved = (run / "config.yaml").read_text()
    assert "my_terms" in saved and "swing_clearance" in saved
    metrics = pd.read_csv(run / "metrics.csv")
    assert (metrics["stage"] == "teacher").sum() == 2
    # the plug-in term has its per-term column like march's own, filled every iteration
    terms = {c for c in metrics.columns if c.startswith("reward/")}
    assert terms == {
        f"reward/{t}"
        for t in ("track_linear_velocity", "alive", "torque", "action_rate", "swing_clearance")
    }
    assert metrics.loc[metrics["stage"] == "teacher", "reward/swing_clearance"].notna().all()


def test_inspect_list_names_the_plugin_term(lab):
    res = _run(lab, "march.inspect", "list", "extra_modules=[my_terms]", lab["search"])
    assert res.returncode == 0, res.stderr[-3000:]
    line = next(ln for ln in res.stdout.splitlines() if ln.strip().startswith("swing_clearance"))
    assert "height=0.05" in line and "[my_terms.swing_clearance]" in line
    assert any(ln.strip().startswith("my_arm") for ln in res.stdout.splitlines())
    sweeps = next(ln for ln in res.stdout.splitlines() if ln.startswith("sweeps "))
    assert "my_sweep" in sweeps.split(": ")[1].split(", ")  # the tree's sweep/ group too
    assert "baseline" in sweeps
