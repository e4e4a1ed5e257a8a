"""Reliability: numerical faults, bad checkpoints, resume with overrides, a full disk.

The kill-and-resume trials are ``scripts/kill_trials.py`` (make kill-trials); the slow test at
the end runs two of them.
"""

from __future__ import annotations

import errno
import math
import os
import random
import subprocess
import sys
from dataclasses import asdict, replace
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf
from saved_runs import resume as _resume
from saved_runs import saved_run as _saved_run
from saved_runs import train_cli as _train
from tool_in_process import run_tool

from march.config import ConfigError
from march.config.cli import load
from march.learn.faults import NumericalFault, UpdateGuard, nonfinite_rows
from march.store.checkpoint import (
    CheckpointError,
    ensure_model_file,
    load_checkpoint,
    save_atomic,
    save_checkpoint,
)
from march.store.resume_rules import RESUME_SAFE

ROOT = Path(__file__).resolve().parent.parent


# ------------------------------------------------------------------ non-finite rows (pure torch)


@pytest.mark.parametrize("seed", range(20))
def test_nonfinite_rows_finds_exactly_the_poisoned_envs(seed):
    g = torch.Generator().manual_seed(seed)
    rng = random.Random(seed)
    n = rng.randint(1, 9)
    obs = {"actor": torch.randn(n, 7, generator=g), "depth": torch.randn(n, 1, 4, 5, generator=g)}
    reward = torch.randn(n, generator=g)
    want = torch.zeros(n, dtype=torch.bool)
    for _ in range(rng.randint(0, 4)):
        env = rng.randrange(n)
        value = rng.choice([math.nan, math.inf, -math.inf])
        target = rng.choice(["actor", "depth", "reward"])
        if target == "reward":
            reward[env] = value
        elif target == "actor":
            obs["actor"][env, rng.randrange(7)] = value
        else:
            obs["depth"][env, 0, rng.randrange(4), rng.randrange(5)] = value
        want[env] = True
    # Huge but finite values are not faults.
    obs["actor"][~want, 0] = 3.0e38
    assert torch.equal(nonfinite_rows(n, obs, reward), want)


# ------------------------------------------------------------------ non-finite updates (pure torch)


def _guarded_sgd(limit: int):
    torch.manual_seed(0)
    model = torch.nn.Linear(3, 2)
    opt = torch.optim.Adam(model.parameters(), lr=0.1)
    guard = UpdateGuard(
        "teacher",
        limit,
        lambda: {"m": model.state_dict(), "o": opt.state_dict()},
        lambda s: (model.load_state_dict(s["m"]), opt.load_state_dict(s["o"])),
        model.parameters,
    )

    def update(poison: bool) -> dict[str, float]:
        x = torch.randn(8, 3)
        if poison:
            x[3, 1] = math.nan  # a poisoned batch: the loss and every gradient become NaN
        loss = model(x).pow(2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        return {"loss": loss.item()}

    return model, opt, guard, update


def test_a_nonfinite_update_is_undone_and_counted():
    model, opt, guard, update = _guarded_sgd(limit=3)
    pattern = [False, True, False, True, True, False, True]
    for it, poison in enumerate(pattern, 1):
        before = {k: v.clone() for k, v in model.state_dict().items()}
        guard.before()
        kept = guard.after(update(poison), it, "teacher/latest.pt")
        after = model.state_dict()
        assert kept is (not poison)
        same = all(torch.equal(before[k], after[k]) for k in before)
        assert same is poison  # undone exactly when poisoned; a good update changes the weights
        assert all(torch.isfinite(p).all() for p in model.parameters())
    assert guard.pop() == sum(pattern) and guard.pop() == 0
    assert guard.in_a_row == 1
    # The optimizer's moments were restored too: a good step after the undone ones is finite.
    guard.before()
    assert guard.after(update(False), 8, None)


def test_too_many_nonfinite_updates_in_a_row_stop_with_one_line():
    model, opt, guard, update = _guarded_sgd(limit=2)
    guard.before()
    assert guard.after(update(True), 5, "run/teacher/latest.pt") is False
    guard.before()
    with pytest.raises(NumericalFault) as err:
        guard.after(update(True), 6, "run/teacher/latest.pt")
    msg = str(err.value)
    assert "\n" not in msg
    assert "iterations 5-6" in msg and "teacher.max_nonfinite_updates=2" in msg
    assert "run/teacher/latest.pt" in msg
    assert all(torch.isfinite(p).all() for p in model.parameters())


def test_max_nonfinite_updates_is_checked_when_composed():
    for section in ("teacher", "distill"):
        assert getattr(load([]), section).max_nonfinite_updates >= 1
        with pytest.raises(ConfigError, match=f"{section}.max_nonfinite_updates=0 must be >= 1"):
            load([f"{section}.max_nonfinite_updates=0"])


# ------------------------------------------------------------------ disk full


def _payload(nbytes: int, it: int) -> dict:
    return {"kind": "teacher", "iteration": it, "w": torch.zeros(nbytes // 4)}


def _no_tmp(directory: Path) -> bool:
    return not [p for p in directory.iterdir() if p.name.endswith(".tmp")]


def test_a_failed_checkpoint_write_keeps_the_previous_one(tmp_path, monkeypatch):
    """A full disk as os.fsync reports it (ENOSPC): at the latest.pt write (the previous one
    stays), and at the model_<it>.pt write that follows (latest.pt is then the new one, whole).
    fsync calls of a save: latest.pt's data, its directory, model_<it>.pt's data, its directory."""
    save_checkpoint(_payload(4000, 1), tmp_path, 1)
    real = os.fsync
    for fail_at, latest_it in ((1, 1), (3, 2)):
        calls = []

        def fsync(fd, calls=calls, fail_at=fail_at):
            calls.append(fd)
            if len(calls) == fail_at:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            return real(fd)

        monkeypatch.setattr(os, "fsync", fsync)
        with pytest.raises(CheckpointError) as err:
            save_checkpoint(_payload(4000, 2), tmp_path, 2)
        monkeypatch.undo()
        msg = str(err.value)
        assert "\n" not in msg and "No space left on device" in msg and "intact" in msg
        assert len(calls) == fail_at
        assert load_checkpoint(tmp_path / "latest.pt", "teacher")["iteration"] == latest_it
        assert load_checkpoint(tmp_path / "model_000001.pt", "teacher")["iteration"] == 1
        assert not (tmp_path / "model_000002.pt").exists()
        assert _no_tmp(tmp_path)


def test_latest_is_the_newest_complete_checkpoint_whenever_a_kill_lands(tmp_path):
    """latest.pt is written before model_<it>.pt: a kill between the two leaves latest.pt the
    newest checkpoint, and the resume writes the model file the kill cut short."""
    from march.store.checkpoint import latest_checkpoint

    assert latest_checkpoint(tmp_path) is None
    save_checkpoint(_payload(400, 2), tmp_path, 2)
    assert latest_checkpoint(tmp_path) == tmp_path / "latest.pt"
    save_atomic(_payload(400, 4), tmp_path / "latest.pt")  # killed right after this
    found = latest_checkpoint(tmp_path)
    assert load_checkpoint(found, "teacher")["iteration"] == 4
    ensure_model_file(load_checkpoint(found, "teacher"), tmp_path)  # what a resume does first
    assert load_checkpoint(tmp_path / "model_000004.pt", "teacher")["iteration"] == 4
    assert load_checkpoint(tmp_path / "model_000002.pt", "teacher")["iteration"] == 2
    assert _no_tmp(tmp_path)
    # Without latest.pt (deleted by hand), the newest model file.
    (tmp_path / "latest.pt").unlink()
    assert latest_checkpoint(tmp_path) == tmp_path / "model_000004.pt"


def _mount_tmpfs(path: Path, size: str) -> bool:
    path.mkdir(parents=True, exist_ok=True)
    if os.geteuid() != 0:
        return False
    out = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)], capture_output=True
    )
    return out.returncode == 0


def test_a_full_file_system_keeps_the_previous_checkpoint(tmp_path):
    """A real full disk: a 1 MiB tmpfs (root only; skipped where it cannot be mounted)."""
    mnt = tmp_path / "small"
    if not _mount_tmpfs(mnt, "1m"):
        pytest.skip("mounting a tmpfs needs root")
    try:
        save_checkpoint(_payload(200_000, 1), mnt, 1)  # two copies: 400 kB of 1 MiB
        with pytest.raises(CheckpointError) as err:
            save_checkpoint(_payload(900_000, 2), mnt, 2)
        assert "No space left on device" in str(err.value) and "\n" not in str(err.value)
        assert load_checkpoint(mnt / "latest.pt", "teacher")["iteration"] == 1
        assert _no_tmp(mnt)
        save_atomic(_payload(100, 3), mnt / "after.pt")  # the space the failed write took is back
    finally:
        subprocess.run(["umount", str(mnt)], check=False)


def test_a_run_on_a_full_disk_stops_with_one_line_and_keeps_its_checkpoint(tmp_path):
    """march.train on a 32 MiB tmpfs: the first teacher checkpoint (2 x 13.5 MB) fits, the
    second does not; the run stops with one line, latest.pt still the first (root only)."""
    mnt = tmp_path / "small"
    if not _mount_tmpfs(mnt, "32m"):
        pytest.skip("mounting a tmpfs needs root")
    try:
        out = _train(
            "compute=smoke",
            "stage=teacher",
            "teacher.max_iterations=3",
            "teacher.num_steps_per_env=2",  # the checkpoints' size does not depend on it
            "teacher.eval_interval=0",
            f"hydra.run.dir={mnt}",
        )
        err = out.stderr.strip().splitlines()
        assert out.returncode == 2, out.stdout[-2000:] + out.stderr[-2000:]
        assert err[-1].startswith("error: could not write checkpoint "), err[-1]
        assert "(No space left on device)" in err[-1] and "Traceback" not in out.stderr
        assert load_checkpoint(mnt / "teacher" / "latest.pt", "teacher")["iteration"] == 1
        assert _no_tmp(mnt / "teacher")
        assert '"failed"' in (mnt / "status.json").read_text()
    finally:
        subprocess.run(["umount", str(mnt)], check=False)


# ------------------------------------------------------------------ resume with overrides


def test_resume_applies_safe_overrides_and_says_so(tmp_path):
    run = _saved_run(tmp_path, "teacher.max_iterations=4", "seed=7")
    cfg, notes = _resume(
        run,
        "teacher.max_iterations=9",
        "distill.eval_interval=3",
        "logger=tensorboard",
        "compute.torch_threads=2",  # the smoke preset's is 1
    )
    assert cfg.teacher.max_iterations == 9 and cfg.distill.eval_interval == 3
    assert cfg.logger.name == "tensorboard" and cfg.compute.torch_threads == 2
    assert cfg.seed == 7 and cfg.compute.name == "smoke"  # the rest is the run's own
    assert cfg.resume == str(run)
    assert "[resume] teacher.max_iterations: 4 -> 9" in notes and len(notes) == 4


def test_resume_with_the_same_values_changes_nothing(tmp_path):
    run = _saved_run(tmp_path, "teacher.max_iterations=4", "seed=7")
    cfg, notes = _resume(run, "compute=smoke", "teacher.max_iterations=4", "seed=7")
    assert notes == [] and cfg.teacher.max_iterations == 4 and cfg.seed == 7


@pytest.mark.parametrize(
    "overrides",
    [
        ["seed=3"],
        ["reward=modelfree"],
        ["student=no_mdn", "eval.num_rollouts=8"],
        ["teacher.learning_rate=0.001", "teacher.max_iterations=9"],
        ["compute=cpu"],
        ["depth.width=64"],
        ["stage=teacher"],
    ],
)
def test_resume_refuses_every_unsafe_override_in_one_line(tmp_path, overrides):
    run = _saved_run(tmp_path)
    with pytest.raises(ConfigError) as err:
        _resume(run, *overrides)
    msg = str(err.value)
    assert "\n" not in msg
    unsafe = [o for o in overrides if not o.startswith("teacher.max_iterations")]
    assert all(o in msg for o in unsafe), msg
    assert "teacher.max_iterations=9" not in msg  # a safe one is not named
    assert all(s in msg for s in RESUME_SAFE)


def test_resume_adds_iterations_but_never_removes_them(tmp_path):
    run = _saved_run(tmp_path, "distill.max_iterations=5")
    with pytest.raises(ConfigError, match="distill.max_iterations=3 is below the run's 5"):
        _resume(run, "distill.max_iterations=3")
    (run / "student").mkdir()
    (run / "student" / "model_000001.pt").write_bytes(b"")
    with pytest.raises(ConfigError, match="cannot change once the distillation has started"):
        _resume(run, "teacher.max_iterations=50")


def test_resume_refuses_a_config_with_an_interpolation(tmp_path):
    run = _saved_run(tmp_path)
    text = (run / "config.yaml").read_text().replace("seed: 0", "seed: ${oc.env:HOME}")
    (run / "config.yaml").write_text(text)
    with pytest.raises(ConfigError, match=r"holds a '\$\{\.\.\.\}' interpolation"):
        _resume(run)


# ------------------------------------------------------------------ CLI: one line, no simulation


def _one_line_before_simulation(out: subprocess.CompletedProcess, *needles: str) -> str:
    # one line in a plain shell: stdout counts too (a library's log line came first there)
    err = [ln for ln in [*out.stdout.splitlines(), *out.stderr.splitlines()] if ln.strip()]
    assert out.returncode == 2, out.stdout[-2000:] + out.stderr[-2000:]
    assert len(err) == 1 and err[0].startswith("error: "), out.stdout + out.stderr
    assert "[env]" not in out.stdout and "Traceback" not in out.stderr  # no env was built
    for n in needles:
        assert n in err[0], err[0]
    return err[0]


def _fake_ckpt(path: Path, kind: str, **cfg_overrides) -> Path:
    """A checkpoint as march.train writes it, minus the weights (the CLI refuses it first)."""
    cfg = load(["compute=smoke", *[f"{k}={v}" for k, v in cfg_overrides.items()]])
    payload = {"kind": kind, "iteration": 1, "env_steps": 32, "config": asdict(cfg)}
    save_atomic(payload, path)
    return path


@pytest.fixture(scope="module")
def ckpts(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("ckpts")
    out = {
        "teacher": _fake_ckpt(d / "teacher.pt", "teacher"),
        "student": _fake_ckpt(d / "student.pt", "student"),
    }
    data = out["student"].read_bytes()
    (d / "truncated.pt").write_bytes(data[: len(data) // 2])
    flipped = bytearray(data)
    for i in range(40, len(flipped), 97):
        flipped[i] ^= 0xFF
    (d / "corrupt.pt").write_bytes(bytes(flipped))
    out["truncated"], out["corrupt"] = d / "truncated.pt", d / "corrupt.pt"
    return out


@pytest.mark.parametrize(
    "args,needles",
    [
        (["stage=eval", "student_ckpt={truncated}"], ["not a readable checkpoint"]),
        (["stage=eval", "student_ckpt={corrupt}"], ["student_ckpt=", "checkpoint"]),
        (["stage=eval", "student_ckpt={teacher}"], ["'teacher' checkpoint, not a student"]),
        (
            ["stage=eval", "eval.policy=teacher", "teacher_ckpt={student}"],
            ["'student' checkpoint, not a teacher"],
        ),
        (["stage=student", "teacher_ckpt={student}"], ["'student' checkpoint, not a teacher"]),
        (
            ["stage=eval", "student_ckpt={student}", "student=no_mdn"],
            ["student=no_mdn conflicts with", "student.variant=full"],
        ),
        (
            ["stage=eval", "student_ckpt={student}", "depth.width=40"],
            ["depth.width=40 conflicts with", "depth.width=32"],
        ),
        (
            ["stage=eval", "student_ckpt={student}", "env.history_length=3"],
            ["env.history_length=3 conflicts with", "env.history_length=5"],
        ),
    ],
)
def test_bad_checkpoints_get_one_line_before_simulation(ckpts, args, needles, capfd):
    out = _train_in_process(capfd, "compute=smoke", *[a.format(**ckpts) for a in args])
    _one_line_before_simulation(out, *needles)


def _train_in_process(capfd, *args: str) -> subprocess.CompletedProcess:
    """``python -m march.train <args>`` run in this process (tests/tool_in_process.py): these
    tests are about the line a refusal prints and its exit status, which a subprocess paid
    ~2 s of CPU for (python, torch); the job log test below keeps a real process."""
    return run_tool(capfd, "march.train", *args)


def test_resume_without_a_run_gets_one_line(tmp_path, capfd):
    (tmp_path / "empty").mkdir()
    _one_line_before_simulation(
        _train_in_process(capfd, f"resume={tmp_path / 'empty'}"), "not a march run directory"
    )
    _one_line_before_simulation(
        _train_in_process(capfd, f"resume={tmp_path / 'nope'}"), "no such run directory"
    )


def test_resume_cli_refuses_an_unsafe_override_and_writes_a_safe_one(tmp_path, ckpts, capfd):
    """Through main: refused overrides leave config.yaml alone; safe ones are written into it
    (this run then stops on its unreadable teacher checkpoint, before any simulation)."""
    run = tmp_path / "run"
    run.mkdir()
    cfg = replace(load(["compute=smoke"]), stage="student", teacher_ckpt=str(ckpts["truncated"]))
    OmegaConf.save(OmegaConf.structured(cfg), run / "config.yaml")
    before = (run / "config.yaml").read_text()
    _one_line_before_simulation(
        _train_in_process(capfd, f"resume={run}", "seed=4", "distill.max_iterations=7"),
        "seed=4 cannot change on resume",
    )
    assert (run / "config.yaml").read_text() == before
    _one_line_before_simulation(
        _train_in_process(capfd, f"resume={run}", "distill.max_iterations=7"),
        "not a readable checkpoint",
    )
    saved = OmegaConf.load(run / "config.yaml")
    assert saved.distill.max_iterations == 7 and saved.seed == 0


def test_a_resume_writes_its_job_log_into_the_run_and_leaves_no_other_folder(
    tmp_path, ckpts, capfd
):
    """A resumed run's Hydra job log goes into the run's own train.log; no new folder appears
    under outputs/, and the run gets no .hydra/ of the resume's (run from an empty working
    directory, so that any folder Hydra made is seen). Before, every resume left one behind."""
    run, cwd = tmp_path / "run", tmp_path / "cwd"
    run.mkdir()
    cwd.mkdir()
    cfg = replace(load(["compute=smoke"]), stage="student", teacher_ckpt=str(ckpts["truncated"]))
    OmegaConf.save(OmegaConf.structured(cfg), run / "config.yaml")
    (run / "train.log").write_text("first launch\n")
    # In this process (tests/tool_in_process.py), from ``cwd``: Hydra writes what it writes
    # there and into the run as a process would; its job log handler is closed afterwards.
    out = run_tool(capfd, "march.train", f"resume={run}", "distill.max_iterations=7", cwd=cwd)
    _one_line_before_simulation(out, "not a readable checkpoint")  # it ran inside the pipeline
    assert list(cwd.iterdir()) == []
    assert not (run / ".hydra").exists()
    assert (run / "train.log").read_text().startswith("first launch\n")


@pytest.mark.parametrize(
    "argv,run_dir",
    [
        (["resume={run}"], "{run}"),
        (["+resume={run}", "distill.max_iterations=7"], "{run}"),
        (["resume={empty}"], None),  # no config.yaml: refused later, nothing redirected
        (["resume={run}/nope"], None),
        (["-m", "resume={run}"], None),  # a sweep's jobs keep their own directories
        (["resume={run}", "hydra.run.dir=/tmp/x"], None),  # set by the caller (ranks > 0)
        (["reward=clf"], None),
    ],
)
def test_only_a_resume_of_a_march_run_is_pointed_at_the_run(tmp_path, argv, run_dir):
    from march.train import _resume_argv

    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "config.yaml").write_text("seed: 0\n")
    (tmp_path / "empty").mkdir()
    names = {"run": tmp_path / "run", "empty": tmp_path / "empty"}
    argv = ["march.train", *[a.format(**names) for a in argv]]
    got = _resume_argv(argv)
    if run_dir is None:
        assert got == argv
    else:
        extra = [f"hydra.run.dir={run_dir.format(**names)}", "hydra.output_subdir=null"]
        assert got == [*argv, *extra]


# ------------------------------------------------------------------ env faults (real smoke env)


@pytest.fixture(scope="module")
def teacher_setup(tmp_path_factory):
    from march.env.build import make_env
    from march.learn.metrics import MetricsLog
    from march.learn.teacher import TeacherRunner

    cfg = load(["compute=smoke", "teacher.max_nonfinite_updates=2"])
    run = tmp_path_factory.mktemp("faults_teacher")
    env = make_env(cfg, "teacher")
    log = MetricsLog(run, cfg.logger, "t")
    runner = TeacherRunner(env, cfg, run, log)
    yield cfg, run, env, runner
    log.close()
    env.close()


def _metric_rows(run: Path, stage: str) -> list[dict]:
    import csv

    with (run / "metrics.csv").open() as f:
        return [r for r in csv.DictReader(f) if r["stage"] == stage]


def test_teacher_resets_nonfinite_envs_and_undoes_nonfinite_updates(teacher_setup, monkeypatch):
    cfg, run, env, runner = teacher_setup
    # Iteration 1: a NaN in env 1's state at step 2, an inf in env 2's observation after step 4,
    # a NaN in env 3's action at step 6: three resets, the run goes on.
    calls = {"step": 0, "act": 0}
    real_step, real_act = runner.env.step, runner.alg.act

    def step(actions):
        calls["step"] += 1
        if calls["step"] == 2:
            env.sim.data.qpos[1, 2] = math.nan
        out = real_step(actions)
        if calls["step"] == 4:
            out[0]["actor"][2, 10] = math.inf
        return out

    def act(obs):
        calls["act"] += 1
        a = real_act(obs)
        if calls["act"] == 6:
            a[3, 0] = math.nan  # in place: the copy rsl-rl stored for the update too
        return a

    monkeypatch.setattr(runner.env, "step", step)
    monkeypatch.setattr(runner.alg, "act", act)
    runner.learn(1)
    row = _metric_rows(run, "teacher")[-1]
    assert int(row["nonfinite_resets"]) == 3 and int(row["nonfinite_updates"]) == 0
    assert all(torch.isfinite(p).all() for p in runner.alg.actor.parameters())
    assert torch.isfinite(env.sim.data.qpos).all()
    # Iteration 2 runs clean: no resets, a finite update.
    monkeypatch.setattr(runner.env, "step", real_step)
    monkeypatch.setattr(runner.alg, "act", real_act)
    runner.learn(2)
    row = _metric_rows(run, "teacher")[-1]
    assert row["iteration"] == "2" and int(row["nonfinite_resets"]) == 0
    # Iterations 3, 4: every update turns the weights to NaN (a poisoned loss): each is undone,
    # the second in a row stops the run (max_nonfinite_updates=2) before its checkpoint.
    good = {k: v.clone() for k, v in runner.alg.actor.state_dict().items()}
    real_update = runner.alg.update

    def update():
        losses = real_update()
        with torch.no_grad():
            for p in runner.alg.actor.parameters():
                p.fill_(math.nan)
        return {**losses, "surrogate": math.nan}

    monkeypatch.setattr(runner.alg, "update", update)
    with pytest.raises(NumericalFault, match="2 updates in a row") as err:
        runner.learn(4)
    assert "\n" not in str(err.value) and "teacher/model_000003.pt" in str(err.value)
    row = _metric_rows(run, "teacher")[-1]
    assert row["iteration"] == "3" and int(row["nonfinite_updates"]) == 1
    assert runner.iteration == 3
    assert load_checkpoint(run / "teacher" / "latest.pt", "teacher")["iteration"] == 3
    for k, v in runner.alg.actor.state_dict().items():
        if v.is_floating_point():
            assert torch.isfinite(v).all(), k
    # Iteration 3's checkpoint holds the weights of iteration 2: its update was undone.
    saved = load_checkpoint(run / "teacher" / "latest.pt", "teacher")["actor_state_dict"]
    assert all(torch.equal(saved[k], good[k]) for k in good if "normalizer" not in k)


def test_distillation_resets_nonfinite_envs_and_undoes_nonfinite_updates(
    teacher_setup, tmp_path, monkeypatch
):
    from march.env.build import make_env
    from march.learn.distill import DistillRunner
    from march.learn.metrics import MetricsLog

    cfg, _, _, teacher = teacher_setup
    cfg = replace(cfg, distill=replace(cfg.distill, max_nonfinite_updates=2))
    env = make_env(cfg, "student")
    log = MetricsLog(tmp_path, cfg.logger, "s")
    try:
        runner = DistillRunner(env, cfg, tmp_path, log, teacher.payload(), "teacher.pt")
        calls = {"step": 0}
        real_step, real_act = env.step, runner.student.act_inference

        def step(actions):
            calls["step"] += 1
            if calls["step"] == 1:
                env.sim.data.qvel[0, 0] = math.inf
            out = real_step(actions)
            if calls["step"] == 3:
                out[0]["depth"][1, 0, 5, 5] = math.nan
            return out

        def act(*inputs):
            a = real_act(*inputs)
            if calls["step"] == 5:  # the action of step 6
                a[2] = math.nan
            return a

        monkeypatch.setattr(env, "step", step)
        monkeypatch.setattr(runner.student, "act_inference", act)
        runner.learn(1)
        row = _metric_rows(tmp_path, "student")[-1]
        assert int(row["nonfinite_resets"]) == 3 and int(row["nonfinite_updates"]) == 0
        assert math.isfinite(float(row["loss"]))
        # A poisoned loss: every update undone, the second in a row stops the run.
        real_loss = runner.student.distill_loss

        def loss(*a, **k):
            value, info = real_loss(*a, **k)
            return value * math.nan, {**info, "loss": math.nan}

        monkeypatch.setattr(runner.student, "distill_loss", loss)
        before = {k: v.clone() for k, v in runner.student.state_dict().items()}
        with pytest.raises(NumericalFault, match="distill.max_nonfinite_updates=2"):
            runner.learn(5)
        assert runner.iteration == 2
        after = runner.student.state_dict()
        params = dict(runner.student.named_parameters())
        assert all(torch.equal(before[k], after[k]) for k in params)
        assert load_checkpoint(tmp_path / "student" / "latest.pt", "student")["iteration"] == 2
    finally:
        log.close()
        env.close()


# ------------------------------------------------------------------ kill trials (slow)


@pytest.mark.slow
def test_kill_trials_before_the_first_checkpoint_and_during_a_write(tmp_path):
    out = subprocess.run(
        [sys.executable, "scripts/kill_trials.py", "--trials", "2", "--out", str(tmp_path)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=1800,
    )
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    assert "resumed 2/2, rows lost 0, rows duplicated 0" in out.stdout
