"""Config composition: every group combination composes and validates; bad input fails clearly."""

from __future__ import annotations

import itertools
import re
import subprocess
import sys

import pytest
from hydra.errors import ConfigCompositionException
from omegaconf.errors import ValidationError

from march.config import COMPUTES, CURRICULA, REWARDS, STUDENTS, ConfigError, MarchConfig
from march.config.cli import compose, load

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
    cfg = load(["+experiment=modelfree", "compute=gpu"])
    assert (cfg.reward.name, cfg.curriculum.name) == ("modelfree", "flat_first")
    assert cfg.teacher.iterations == 20000
    assert load(["+experiment=clf", "compute=gpu"]).teacher.iterations == 10000


def test_sweeps_compose():
    assert load(["+sweep=baseline"]).stage == "all"
    assert load(["+sweep=ablation", "teacher_ckpt=x.pt"]).stage == "student"
    out = _train("+sweep=baseline", "--cfg", "hydra")
    assert out.returncode == 0, out.stderr
    assert "+experiment: clf,modelfree" in out.stdout and "seed: 0,1,2" in out.stdout
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


@pytest.mark.parametrize("arg", ["+arm=clf", "arm=modelfree", "+arm/x=clf"])
def test_renamed_group_is_refused_in_one_line_naming_the_new_override(arg, tmp_path):
    """conf/arm/ became conf/experiment/: the old choice says what to write, nothing is run."""
    out = _train("compute=smoke", arg, f"hydra.run.dir={tmp_path}/r")
    assert out.returncode == 2
    (line,) = [ln for ln in [*out.stdout.splitlines(), *out.stderr.splitlines()] if ln.strip()]
    assert "+experiment=" in line and arg in line, line
    assert not (tmp_path / "r").exists()


def test_renamed_group_check_leaves_other_overrides_alone():
    from march.config.cli import renamed_group

    ok = ["+experiment=clf", "reward=clf", "armature=1", "env.arm=2", "seed=0"]
    assert renamed_group(ok) is None
    assert renamed_group([*ok, "+arm=modelfree"]) is not None


def test_cli_bad_value_and_missing_checkpoint_are_one_line_errors(tmp_path):
    out = _train("compute=smoke", "compute.num_envs=0", f"hydra.run.dir={tmp_path}/a")
    assert out.returncode == 2
    both = [ln for ln in [*out.stdout.splitlines(), *out.stderr.splitlines()] if ln.strip()]
    assert both == ["error: compute.num_envs=0 must be > 0"]  # stdout too: a plain shell's view
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


# ------------------------------------------------------- a checkpoint defines its policy


def _payload(overrides: list[str], kind: str = "student") -> dict:
    """What march.train saves: ``dataclasses.asdict`` of the config a checkpoint trained with."""
    from dataclasses import asdict

    return {"kind": kind, "config": asdict(load(["compute=smoke", *overrides]))}


TRAINED = [
    "reward=modelfree",
    "curriculum=flat_first",
    "student=no_mdn",
    "student.d_model=64",
    "student.n_heads=4",
    "env.history_length=3",
    "depth.width=16",
]


def test_checkpoint_policy_replaces_the_command_line_defaults():
    from march.store.provenance import apply_checkpoint_config, policy_changes

    today = ["compute=smoke", "stage=eval", "seed=7", "eval.num_rollouts=3", "dr=none"]
    cfg = load(today)
    new = apply_checkpoint_config(cfg, _payload(TRAINED), today, "s.pt", "student")
    trained = load(["compute=smoke", *TRAINED])
    assert new.reward == trained.reward  # name, every term weight (none of clf's left over)
    assert set(new.reward.terms) == set(trained.reward.terms) and "clf" not in new.reward.terms
    assert new.student == trained.student
    assert (new.env.history_length, new.depth.width) == (3, 16)
    assert (new.curriculum.name, new.curriculum.flat_levels) == ("flat_first", 2)
    # The evaluation protocol stays the user's.
    assert (new.seed, new.eval.num_rollouts, new.dr.name, new.compute) == (
        7,
        3,
        "none",
        cfg.compute,
    )
    assert new.stage == "eval" and new.depth.noise_scale == cfg.depth.noise_scale
    changes = policy_changes(cfg, new, "student")
    assert "reward.name: clf -> modelfree" in changes
    assert "student.variant: full -> no_mdn" in changes and "env.history_length: 5 -> 3" in changes


@pytest.mark.parametrize(
    ("explicit", "named"),
    [
        (["reward=clf"], ("reward=clf", "reward.name=modelfree")),
        (["+experiment=clf"], ("+experiment=clf", "reward.name=modelfree")),
        (["student=full"], ("student=full", "student.variant=no_mdn")),
        (["student.variant=full"], ("student.variant=full", "student.variant=no_mdn")),
        (["student.d_model=256", "student.n_heads=8"], ("student.d_model=256", "=64")),
        (["env.history_length=5"], ("env.history_length=5", "env.history_length=3")),
        (["depth.width=32"], ("depth.width=32", "depth.width=16")),
        (["reward=modelfree", "reward.terms.alive=2"], ("reward.terms.alive=2", "alive=0.5")),
        (["reward.terms.clf=3"], ("reward.terms.clf=3", "reward.terms=")),
        (["curriculum=stones"], ("curriculum=stones", "curriculum.name=flat_first")),
    ],
)
def test_conflicting_explicit_choice_is_one_line_naming_both(explicit, named):
    from march.store.provenance import apply_checkpoint_config

    cfg = load(["compute=smoke", "stage=eval", *explicit])
    with pytest.raises(ConfigError) as err:
        apply_checkpoint_config(cfg, _payload(TRAINED), explicit, "ckpt/s.pt", "student")
    text = str(err.value)
    assert "\n" not in text and "student_ckpt=ckpt/s.pt" in text
    assert all(n in text for n in named), text


@pytest.mark.parametrize(
    "explicit",
    [
        ["reward=modelfree", "student=no_mdn", "curriculum=flat_first"],
        [
            "student.d_model=64",
            "env.history_length=3",
            "reward=modelfree",
            "reward.terms.alive=0.5",
        ],
        ["seed=3", "eval.num_rollouts=5", "dr=none", "compute.num_envs=2", "depth.dropout=0.2"],
        ["hydra.run.dir=/tmp/x", "+sweep=ablation"],
    ],
)
def test_agreeing_or_protocol_choices_are_accepted(explicit):
    from march.store.provenance import apply_checkpoint_config

    cfg = load(["compute=smoke", *explicit])
    new = apply_checkpoint_config(cfg, _payload(TRAINED), explicit, "s.pt", "student")
    assert (new.reward.name, new.student.variant, new.student.d_model) == (
        "modelfree",
        "no_mdn",
        64,
    )


def test_teacher_checkpoint_keeps_the_users_student_and_distillation_curriculum():
    from march.store.provenance import apply_checkpoint_config

    teacher = _payload(["reward=modelfree", "curriculum=flat_first", "teacher.hidden_dims=[8,8]"])
    explicit = ["stage=student", "student=no_mdn", "curriculum=stones"]
    cfg = load(["compute=smoke", *explicit])
    new = apply_checkpoint_config(cfg, teacher, explicit, "t.pt", "teacher", distill=True)
    assert new.reward.name == "modelfree" and list(new.teacher.hidden_dims) == [8, 8]
    assert (new.student.variant, new.curriculum.name) == ("no_mdn", "stones")
    # Evaluating the teacher: the curriculum is its label, the student section is not its.
    cfg = load(["compute=smoke", "stage=eval", "eval.policy=teacher", "student=no_mdn"])
    new = apply_checkpoint_config(cfg, teacher, ["student=no_mdn"], "t.pt", "teacher")
    assert (new.curriculum.name, new.student.variant) == ("flat_first", "no_mdn")
    with pytest.raises(ConfigError, match="reward=clf conflicts with teacher_ckpt=t.pt"):
        apply_checkpoint_config(cfg, teacher, ["reward=clf"], "t.pt", "teacher")


def test_checkpoint_without_config_is_a_clear_error():
    from march.store.provenance import apply_checkpoint_config

    with pytest.raises(ConfigError, match="carries no saved config"):
        apply_checkpoint_config(load(["compute=smoke"]), {"kind": "student"}, [], "x.pt", "student")


def test_checkpoint_from_an_older_schema_keeps_missing_fields():
    from march.store.provenance import apply_checkpoint_config

    payload = _payload(["reward=modelfree"])
    del payload["config"]["student"]["huber_delta"], payload["config"]["depth"]
    cfg = load(["compute=smoke", "student.huber_delta=0.3"])
    new = apply_checkpoint_config(cfg, payload, [], "x.pt", "student")
    assert new.reward.name == "modelfree" and new.student.huber_delta == 0.3


def test_run_dirs_are_named_after_the_resolved_preset():
    import hydra

    from march.config.cli import CONF_DIR

    for compute, suffix in (("auto", "cpu"), ("smoke", "smoke"), ("gpu", "gpu")):
        with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = hydra.compose(
                config_name="config",
                overrides=[f"compute={compute}", "reward=modelfree"],
                return_hydra_config=True,
            )
        # no CUDA here; then the seed and this process's unique part (pid-random)
        assert re.search(
            rf"_modelfree_full_{suffix}_seed0_[0-9a-f]+-[0-9a-f]{{6}}$", cfg.hydra.run.dir
        )
        assert re.search(rf"_{suffix}_[0-9a-f]+-[0-9a-f]{{6}}$", cfg.hydra.sweep.dir)


def test_compute_is_never_a_sweep_parameter(tmp_path):
    """A sweep over the compute preset splits its directories (issue 24): refused in one line,
    from a sweep file's hydra.sweeper.params and from a -m command line; one value is fine."""
    from march.config.sweeps import sweep_problem

    (tmp_path / "scaled.yaml").write_text(
        "hydra:\n  sweeper:\n    params:\n      compute: cpu,smoke\n      seed: 0,1\n"
    )
    (tmp_path / "pinned.yaml").write_text(
        "defaults:\n  - override /compute: smoke\nhydra:\n  sweeper:\n    params:\n"
        "      seed: 0,1\n"
    )
    msg = sweep_problem(["-m", "+sweep=scaled"], tmp_path)
    assert "hydra.sweeper.params.compute" in msg and "defaults" in msg and "\n" not in msg
    assert sweep_problem(["-m", "+sweep=pinned"], tmp_path) is None
    assert "compute cannot be swept" in sweep_problem(["-m", "compute=cpu,smoke"], tmp_path)
    assert sweep_problem(["-m", "compute=smoke", "seed=0,1"], tmp_path) is None
    assert sweep_problem(["compute=cpu,smoke"], tmp_path) is None  # not a multirun
    for real in sorted((ROOT / "sweeps").glob("*.yaml")):
        assert sweep_problem(["-m", f"+sweep={real.stem}"]) is None, real.name
    # a sweep in a user's config tree (hydra.searchpath, its sweep/ group) is checked the same way
    tree = tmp_path / "my_conf"
    (tree / "sweep").mkdir(parents=True)
    (tree / "sweep" / "mine.yaml").write_text((tmp_path / "scaled.yaml").read_text())
    search = f"hydra.searchpath=[file://{tree}]"
    msg = sweep_problem(["-m", "+sweep=mine", search], tmp_path / "empty")
    assert "mine.yaml: hydra.sweeper.params.compute" in msg and "\n" not in msg
    assert sweep_problem(["-m", "+sweep=mine"], tmp_path / "empty") is None  # not on the path
    # a tree's sweep named like one of the repository's is the one Hydra runs, so it is checked
    repo = tmp_path / "repo"
    repo.mkdir()
    (repo / "mine.yaml").write_text((tmp_path / "pinned.yaml").read_text())
    assert "mine.yaml: hydra.sweeper.params.compute" in sweep_problem(
        ["-m", "+sweep=mine", search], repo
    )
    assert sweep_problem(["-m", "+sweep=mine"], repo) is None
