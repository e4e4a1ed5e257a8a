"""Config composition: every group combination composes and validates; bad input fails clearly."""

from __future__ import annotations

import itertools
import subprocess
import sys

import pytest
from hydra.errors import ConfigCompositionException
from omegaconf.errors import ValidationError

from march.cli import compose, load
from march.config import COMPUTES, CURRICULA, REWARDS, STUDENTS, ConfigError, MarchConfig

ROOT = __import__("pathlib").Path(__file__).resolve().parent.parent


@pytest.mark.parametrize(
    "reward,student,curriculum,compute",
    list(itertools.product(REWARDS, STUDENTS, CURRICULA, COMPUTES)),
)
def test_every_combination_composes(reward, student, curriculum, compute):
    cfg = load(
        [f"reward={reward}", f"student={student}", f"curriculum={curriculum}", f"compute={compute}"]
    )
    assert isinstance(cfg, MarchConfig)
    assert (cfg.reward.name, cfg.student.variant, cfg.curriculum.name) == (
        reward,
        student,
        curriculum,
    )
    # auto resolves to a concrete preset (no CUDA here -> cpu)
    assert cfg.compute.name == (compute if compute != "auto" else "cpu")
    assert cfg.reward.terms, "every reward option names its terms"


def test_paper_values_are_the_defaults():
    cfg = load(["compute=gpu"])
    t, d = cfg.teacher, cfg.distill
    assert (cfg.compute.num_envs, t.max_iterations, d.max_iterations, cfg.eval.num_rollouts) == (
        4096,
        10000,
        1500,
        2048,
    )
    assert (t.learning_rate, t.num_learning_epochs, t.num_mini_batches, t.entropy_coef) == (
        5e-5,
        5,
        4,
        0.008,
    )
    assert (t.gamma, t.lam, t.desired_kl, t.num_steps_per_env) == (0.99, 0.95, 0.01, 24)
    assert tuple(t.hidden_dims) == (512, 256, 128)
    assert (d.learning_rate, d.num_learning_epochs, d.gradient_length, d.max_grad_norm) == (
        5e-4,
        10,
        2,
        2.0,
    )
    assert (d.teacher_samples, d.teacher_std_scale, d.num_steps_per_env) == (8, 0.1, 120)
    assert (cfg.student.num_modes, cfg.student.min_std) == (2, 1e-3)
    assert (cfg.student.log_std_min, cfg.student.log_std_max) == (-3.0, 2.0)


def test_auto_keeps_user_overrides():
    cfg = load(["compute=auto", "compute.num_envs=64", "teacher.max_iterations=7"])
    assert (cfg.compute.name, cfg.compute.num_envs, cfg.teacher.max_iterations) == ("cpu", 64, 7)


def test_baseline_arm_pins_curriculum_and_budget():
    cfg = load(["+arm=modelfree", "compute=gpu"])
    assert (cfg.reward.name, cfg.curriculum.name) == ("modelfree", "flat_first")
    assert cfg.teacher.iterations == 20000
    assert load(["+arm=clf", "compute=gpu"]).teacher.iterations == 10000


def test_sweeps_compose():
    assert load(["+sweep=baseline"]).stage == "all"
    assert load(["+sweep=ablation", "teacher_ckpt=x.pt"]).stage == "student"
    out = _train("+sweep=baseline", "--cfg", "hydra")
    assert out.returncode == 0, out.stderr
    assert "+arm: clf,modelfree" in out.stdout and "seed: 0,1,2" in out.stdout
    out = _train("+sweep=ablation", "--cfg", "hydra")
    assert "student: full,no_transformer,no_mdn" in out.stdout


def test_unknown_option_names_valid_ones():
    with pytest.raises(ConfigCompositionException) as err:
        compose(["reward=bogus"])
    assert "clf" in str(err.value) and "modelfree" in str(err.value)


def test_unknown_key_and_wrong_type_fail_at_composition():
    with pytest.raises(ConfigCompositionException):
        compose(["teacher.learnin_rate=1e-3"])
    with pytest.raises((ConfigCompositionException, ValidationError)):
        compose(["compute.num_envs=many"])


@pytest.mark.parametrize(
    "override,needle",
    [
        ("compute.num_envs=0", "compute.num_envs=0 must be > 0"),
        ("stage=train", "stage='train' is not valid"),
        ("eval.course=moon", "eval.course='moon'"),
        ("curriculum.flat_levels=3", "curriculum=stones has no flat levels"),
        ("depth.dropout=1.5", "depth.dropout=1.5"),
    ],
)
def test_impossible_values_raise_config_error(override, needle):
    with pytest.raises(ConfigError, match=needle.replace("(", r"\(").replace("[", r"\[")):
        load([override])


def _train(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "march.train", *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_cli_bogus_reward_exits_nonzero_with_options():
    out = _train("compute=smoke", "reward=bogus")
    assert out.returncode != 0
    text = out.stderr + out.stdout
    assert "reward/bogus" in text and "clf" in text and "modelfree" in text


def test_cli_bad_value_and_missing_checkpoint_are_one_line_errors(tmp_path):
    out = _train("compute=smoke", "compute.num_envs=0", f"hydra.run.dir={tmp_path}/a")
    assert out.returncode == 2
    assert out.stderr.strip().splitlines() == ["error: compute.num_envs=0 must be > 0"]
    out = _train(
        "compute=smoke", "stage=student", "teacher_ckpt=/nope.pt", f"hydra.run.dir={tmp_path}/b"
    )
    assert out.returncode == 2
    assert out.stderr.strip() == "error: teacher_ckpt=/nope.pt: no such file"
    assert not (tmp_path / "b" / "teacher").exists()  # nothing started


def test_cli_cfg_hydra_shows_choices():
    out = _train("--cfg", "hydra", "reward=modelfree", "student=no_mdn", "curriculum=flat_first")
    assert out.returncode == 0, out.stderr
    assert "reward: modelfree" in out.stdout
    assert "student: no_mdn" in out.stdout
    assert "curriculum: flat_first" in out.stdout
