"""A run directory is owned and guarded (docs/reliability.md): one owner, one writer, checked
before Hydra starts, everything read from disk validated, no write through a link, preemption
visible. One section per item of issue 38; the CLI tests run ``python -m march.train`` and
stop before any env is built (a few seconds each), the end-to-end preemption test is slow."""

from __future__ import annotations

import json
import os
import random
import signal
import socket
import subprocess
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

import pytest
from omegaconf import OmegaConf
from saved_runs import saved_run as _saved_run
from saved_runs import train_cli
from tool_in_process import run_tool

from march.config import ConfigError
from march.config.cli import check_output_dir, duplicate_overrides, literal_prefix, load
from march.config.memory import SIM_BYTES_PER_ENV, check_memory, estimate
from march.learn import preemption
from march.learn.metrics import METRIC_COLUMNS, append_row
from march.store import run_lock
from march.store.checkpoint import save_atomic
from march.store.gate import check_checkpoint
from march.store.resume_rules import RESUME_SAFE, adopt_config
from march.store.run_dir import before_hydra, check_run_checkpoints, refuse_links

ROOT = Path(__file__).resolve().parent.parent


def _train(capfd, *args: str) -> subprocess.CompletedProcess:
    """``python -m march.train <args>`` run in this process (tests/tool_in_process.py): the CLI
    tests here check the line a refusal prints, its exit status and what it left on disk, which
    a subprocess paid ~2 s of CPU for; what the refusal imports is checked in a real process
    (``_train_listing_modules``)."""
    return run_tool(capfd, "march.train", *args)


def _one_line(out: subprocess.CompletedProcess, *needles: str) -> str:
    # one line in a plain shell: stdout counts too (a library's log line came first there)
    err = [ln for ln in [*out.stdout.splitlines(), *out.stderr.splitlines()] if ln.strip()]
    assert out.returncode == 2, out.stdout[-2000:] + out.stderr[-2000:]
    assert len(err) == 1 and err[0].startswith("error: "), out.stdout + out.stderr
    assert "[env]" not in out.stdout and "Traceback" not in out.stderr
    for n in needles:
        assert n in err[0], err[0]
    return err[0]


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {
        p.relative_to(folder).as_posix(): p.read_bytes() for p in folder.rglob("*") if p.is_file()
    }


# ------------------------------------------------------------------ 1. one owner per run directory


UNSAFE = [
    ("seed", "5"),
    ("reward", "modelfree"),
    ("compute.num_envs", "8"),
    ("env.history_length", "3"),
    ("teacher.learning_rate", "0.002"),
    ("curriculum", "flat_first"),
    ("stage", "teacher"),
]


@pytest.mark.parametrize("key,value", UNSAFE)
def test_a_new_run_in_a_run_directory_is_refused_naming_the_key(tmp_path, key, value):
    run = _saved_run(tmp_path)
    with pytest.raises(ConfigError) as err:
        adopt_config(run, load(["compute=smoke", f"{key}={value}"]))
    line = str(err.value)
    assert "\n" not in line and "already holds a run" in line and f"resume={run}" in line
    name = {"reward": "reward.name", "curriculum": "curriculum.name"}.get(key, key)
    assert f"{name}:" in line, line


def test_the_same_config_continues_the_run_and_safe_changes_apply(tmp_path):
    run = _saved_run(tmp_path)
    cfg, notes = adopt_config(run, load(["compute=smoke"]))
    assert cfg == load(["compute=smoke"]) and len(notes) == 1
    more, notes = adopt_config(run, load(["compute=smoke", "distill.max_iterations=9"]))
    assert more.distill.max_iterations == 9 and any("distill.max_iterations" in n for n in notes)
    with pytest.raises(ConfigError, match="can only be added"):
        adopt_config(run, load(["compute=smoke", "distill.max_iterations=1"]))


@pytest.mark.parametrize("case", range(12))
def test_every_difference_outside_the_safe_list_is_refused(tmp_path, case):
    """Random sets of unsafe overrides: all of them named, none of the safe ones."""
    rng = random.Random(case)
    picked = rng.sample(UNSAFE, rng.randint(1, 3))
    run = _saved_run(tmp_path)
    with pytest.raises(ConfigError) as err:
        adopt_config(run, load(["compute=smoke", *[f"{k}={v}" for k, v in picked]]))
    for key, _ in picked:
        name = {"reward": "reward.name", "curriculum": "curriculum.name"}.get(key, key)
        assert f"{name}:" in str(err.value)
    assert not any(f"{s}:" in str(err.value) for s in RESUME_SAFE if "." in s)


def test_cli_new_run_with_another_seed_leaves_the_run_untouched(tmp_path, capfd):
    run = _saved_run(tmp_path)
    (run / ".hydra").mkdir()
    (run / ".hydra" / "overrides.yaml").write_text("- compute=smoke\n")
    (run / "train.log").write_text("first launch\n")
    before = _snapshot(run)
    line = _one_line(
        _train(capfd, "compute=smoke", "seed=5", f"hydra.run.dir={run}"),
        "already holds a run with another config (seed: 0 -> 5)",
    )
    assert f"resume={run}" in line
    assert _snapshot(run) == before  # config.yaml, .hydra/ and train.log as they were


def test_cli_new_run_in_a_folder_of_run_files_without_config_is_refused(tmp_path, capfd):
    run = tmp_path / "run"
    (run / "teacher").mkdir(parents=True)
    (run / "metrics.csv").write_text("stage,iteration\n")
    _one_line(_train(capfd, "compute=smoke", f"hydra.run.dir={run}"), "no config.yaml")
    assert not (run / "config.yaml").exists()


# ------------------------------------------------------------------ 2. one writer at a time

_HOLD = """
import sys, time
from march.store import run_lock
run_lock.acquire(sys.argv[1])
print("held", flush=True)
time.sleep(120)
"""


def _holder(run: Path) -> subprocess.Popen:
    proc = subprocess.Popen(
        [sys.executable, "-c", _HOLD, str(run)], cwd=ROOT, stdout=subprocess.PIPE, text=True
    )
    assert proc.stdout.readline().strip() == "held"
    return proc


def test_a_second_writer_is_refused_naming_the_holder(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    proc = _holder(run)
    try:
        with pytest.raises(run_lock.RunLocked) as err:
            run_lock.acquire(run, "resume")
        line = str(err.value)
        assert f"pid {proc.pid} on host {socket.gethostname()}" in line and "\n" not in line
        assert f"resume={run} is in use" in line
    finally:
        proc.kill()
        proc.wait()
    # The holder is gone (SIGKILL: no clean-up ran): its lock is stale and is taken over.
    info = json.loads((run / "run.lock").read_text())
    assert info["pid"] == proc.pid
    lock = run_lock.acquire(run, "resume")
    try:
        assert lock.stale["pid"] == proc.pid
        assert f"pid {proc.pid}" in run_lock.stale_note(lock)
        assert json.loads((run / "run.lock").read_text())["pid"] == os.getpid()
    finally:
        lock.release()
    assert not (run / "run.lock").exists()


def test_cli_two_concurrent_resumes_the_second_writes_nothing(tmp_path, capfd):
    run = _saved_run(tmp_path)
    (run / "train.log").write_text("first launch\n")
    (run / "status.json").write_text('{"state": "running"}')
    proc = _holder(run)
    try:
        before = _snapshot(run)
        line = _one_line(_train(capfd, f"resume={run}"), f"is in use by pid {proc.pid} on host")
        assert "nothing was written" in line
        assert _snapshot(run) == before
    finally:
        proc.kill()
        proc.wait()


# ------------------------------------------------------------------ 3. checked before Hydra starts


def test_output_directory_checks(tmp_path):
    (tmp_path / "file").write_text("x")
    check_output_dir(tmp_path / "new" / "deeper", "hydra.run.dir")  # creatable
    check_output_dir(tmp_path, "hydra.run.dir")  # an existing writable directory
    with pytest.raises(ConfigError, match="is a file, not a directory"):
        check_output_dir(tmp_path / "file" / "run", "hydra.run.dir")
    with pytest.raises(ConfigError, match="cannot create directories in /proc"):
        check_output_dir("/proc/march_no_such/run", "hydra.run.dir")
    os.symlink(tmp_path / "gone", tmp_path / "dangling")
    with pytest.raises(ConfigError, match="broken symbolic link"):
        check_output_dir(tmp_path / "dangling" / "run", "hydra.run.dir")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dangling", "file"]  # probes removed
    assert literal_prefix("outputs/${now:%Y}/x") == Path("outputs")
    assert literal_prefix("/a/b${now:%H}/c") == Path("/a")
    assert literal_prefix("/a/b/c") == Path("/a/b/c")


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into a read-only directory")
def test_a_read_only_directory_is_refused(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        with pytest.raises(ConfigError, match="cannot create directories in"):
            check_output_dir(ro / "run", "hydra.run.dir")
    finally:
        ro.chmod(0o755)


def test_cli_a_read_only_file_system_gets_one_line(tmp_path, capfd):
    """A real read-only mount (a tmpfs remounted ro; root only, skipped elsewhere): a new run
    under it and a resume of a run on it each end in one line (before: Hydra's tracebacks)."""
    mnt = tmp_path / "ro"
    mnt.mkdir()
    if (
        os.geteuid() != 0
        or subprocess.run(
            ["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(mnt)], capture_output=True
        ).returncode
    ):
        pytest.skip("mounting a tmpfs needs root")
    try:
        run = _saved_run(mnt)
        subprocess.run(["mount", "-o", "remount,ro", str(mnt)], check=True)
        _one_line(
            _train(capfd, "compute=smoke", f"hydra.run.dir={mnt}/new"),
            f"cannot create directories in {mnt} (Read-only file system)",
        )
        _one_line(_train(capfd, f"resume={run}"), "cannot create run.lock (Read-only file system)")
        assert sorted(p.name for p in run.iterdir()) == ["config.yaml"]
    finally:
        subprocess.run(["umount", str(mnt)], check=False)


@pytest.mark.parametrize("case", range(20))
def test_a_key_set_twice_is_found_in_generated_command_lines(case):
    rng = random.Random(case)
    keys = ["seed", "compute.num_envs", "reward", "teacher.max_iterations", "hydra.run.dir"]
    chosen = rng.sample(keys, rng.randint(1, len(keys)))
    args = [f"{k}={rng.randint(1, 9)}" for k in chosen]
    assert duplicate_overrides(args) is None
    dup = rng.choice(chosen)
    prefix = rng.choice(["", "+", "++"])
    args.insert(rng.randint(0, len(args)), f"{prefix}{dup}={rng.randint(10, 20)}")
    line = duplicate_overrides(["-m", *args])
    assert line is not None and line.startswith(f"{dup} is set twice")


def test_memory_estimate_by_hand():
    cfg = load(["compute=smoke"])
    parts = estimate(cfg)
    frame = 96 * 5 * 4  # proprio floats x history x float32
    depth = 32 * 24 * 4
    teacher = 8 * (2 * frame + (3 * 29 + 4) * 4)
    student = 8 * (frame + depth + 2 * 29 * 4)
    assert parts["simulator state"] == (4 + 4) * SIM_BYTES_PER_ENV
    assert parts["observations"] == (4 + 4) * (2 * frame + depth)
    assert parts["rollout storage"] == 4 * max(teacher, student)
    for preset in ("smoke", "cpu"):
        check_memory(load([f"compute={preset}"]))  # the presets fit this machine
    big = replace(cfg, compute=replace(cfg.compute, num_envs=2_000_000_000))
    with pytest.raises(ConfigError) as err:
        check_memory(big)
    assert "compute.num_envs=2000000000" in str(err.value) and "need at least" in str(err.value)


def test_cli_impossible_directories_and_sizes_get_one_line(tmp_path, capfd):
    _one_line(
        _train(capfd, "hydra.run.dir=/etc/passwd/run"), "/etc/passwd is a file, not a directory"
    )
    _one_line(
        _train(capfd, "compute=smoke", "compute.num_envs=4", "compute.num_envs=8"),
        "compute.num_envs is set twice",
    )
    big, modules = tmp_path / "big", tmp_path / "modules.txt"
    _one_line(
        _train_listing_modules(
            modules, "compute=smoke", "compute.num_envs=2000000000", f"hydra.run.dir={big}"
        ),
        "compute.num_envs=2000000000",
        "need at least",
    )
    # refused at once: no env built, Warp never started (so no kernel compiled or loaded), and
    # nothing left on disk; observables, not a wall-clock limit that a busy machine breaks
    loaded = set(modules.read_text().split())
    assert {"hydra", "march.config.memory"} <= loaded  # the listing works
    # the reward terms are checked against march's term table, so not even mjlab is imported
    built = loaded & {"mjlab", "march.env.build", "march.learn.teacher", WARP_STARTED}
    assert not built, sorted(built)
    assert not big.exists()


WARP_STARTED = "<warp-runtime-started>"


def _train_listing_modules(listing: Path, *args: str) -> subprocess.CompletedProcess:
    """``python -m march.train <args>`` as :func:`saved_runs.train_cli` runs it, writing into
    ``listing``, as it exits (however it exits), the names of every module it imported, and
    ``WARP_STARTED`` if Warp's runtime was initialised (what compiling or loading a kernel
    takes; the term checks import mjlab, and so Warp, without starting it)."""
    code = f"""
import atexit, runpy, sys

def _list():
    warp = sys.modules.get("warp._src.context")
    started = [{WARP_STARTED!r}] if getattr(warp, "runtime", None) is not None else []
    open({str(listing)!r}, "w").write(" ".join([*sys.modules, *started]))

atexit.register(_list)
sys.argv[0] = "march.train"
runpy.run_module("march.train", run_name="__main__", alter_sys=True)
"""
    return subprocess.run(
        [sys.executable, "-c", code, *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        env=dict(os.environ, HYDRA_FULL_ERROR="0"),
    )


def test_before_hydra_leaves_a_new_directory_to_hydra_and_locks_an_existing_run(tmp_path):
    argv = ["march.train", f"hydra.run.dir={tmp_path / 'new'}"]
    assert before_hydra(argv, multirun=False) == argv and not (tmp_path / "new").exists()
    run = _saved_run(tmp_path)
    got = before_hydra(["march.train", "compute=smoke", f"hydra.run.dir={run}"], multirun=False)
    try:
        assert got[-1] == "hydra.output_subdir=null"
        assert json.loads((run / "run.lock").read_text())["pid"] == os.getpid()
        # Another config is refused here, before Hydra writes its job log into the run.
        with pytest.raises(ConfigError, match=r"another config \(seed: 0 -> 5\)"):
            before_hydra(["m", "compute=smoke", "seed=5", f"hydra.run.dir={run}"], False)
    finally:
        run_lock.release_all()


# ------------------------------------------------------------------ 4. checkpoints validated


def _payload(kind: str = "teacher", **config_changes) -> dict:
    cfg = asdict(load(["compute=smoke"]))
    for dotted, value in config_changes.items():
        node = cfg
        *parents, leaf = dotted.split(".")
        for p in parents:
            node = node[p]
        node[leaf] = value
    payload = {"kind": kind, "iteration": 2, "env_steps": 64, "wall_s": 1.5, "config": cfg}
    return _with_weights(payload, kind)


def _with_weights(payload: dict, kind: str) -> dict:
    """The layout and (zero) weights of the network the smoke config describes: what the disk
    gate compares a checkpoint's weights with."""
    from march.learn.teacher import ppo_train_cfg
    from march.store.gate import network_weights

    cfg = load(["compute=smoke"])
    if kind == "teacher":
        payload["layout"] = {"actor_obs_dim": 764, "num_actions": 29}
        payload["ppo"] = ppo_train_cfg(cfg.teacher)
        payload["actor_state_dict"] = network_weights(payload, kind, cfg)
    else:
        payload["layout"] = {
            "variant": "full",
            "proprio_dim": 96,
            "history_len": cfg.env.history_length,
            "image_hw": [cfg.depth.height, cfg.depth.width],
            "num_actions": 29,
        }
        payload["student_state_dict"] = network_weights(payload, kind, cfg)
    return payload


@pytest.mark.parametrize(
    "change,needle",
    [
        ({"config": {"reward.label": "${oc.env:HOME}"}}, "reward.label holds a '${...}'"),
        ({"config": {"seed": "${oc.decode:'1'}"}}, "seed holds a '${...}'"),
        ({"config": {"env.history_length": 10**9}}, "need at least"),
        ({"config": {"reward.terms.clf": "abc"}}, "its config is not valid"),
        ({"config": {"compute.num_envs": -3}}, "its config is not valid"),
        ({"iteration": "../../x"}, "its iteration '../../x'"),
        ({"iteration": -1}, "its iteration -1"),
        ({"iteration": True}, "its iteration True"),
        ({"iteration": 10**12}, "its iteration"),
        ({"iteration": 5, "env_steps": 160}, "past its config's 2 iterations"),
        ({"env_steps": 65}, "not a multiple of 32"),
        ({"env_steps": 32}, "at least iteration x 32"),
        ({"env_steps": 2.0}, "its env_steps 2.0"),
        ({"wall_s": float("nan")}, "its wall_s nan"),
    ],
)
def test_a_crafted_checkpoint_is_refused_in_one_line(change, needle):
    payload = _payload(**change.get("config", {}))
    payload.update({k: v for k, v in change.items() if k != "config"})
    with pytest.raises(ConfigError) as err:
        check_checkpoint(payload, "teacher", "teacher_ckpt=x.pt")
    assert needle in str(err.value) and "\n" not in str(err.value), str(err.value)
    assert str(err.value).startswith("teacher_ckpt=x.pt: ")


def test_a_checkpoint_march_wrote_passes():
    assert check_checkpoint(_payload(), "teacher", "x") == load(["compute=smoke"])
    assert check_checkpoint(_payload("student"), "student", "x") is not None
    old = _payload()
    del old["config"]
    assert check_checkpoint(old, "teacher", "x") is None


def test_a_run_checkpoint_is_checked_before_any_env(tmp_path, capfd):
    run = _saved_run(tmp_path)
    cfg = load(["compute=smoke"])
    (run / "teacher").mkdir()
    save_atomic(_payload(), run / "teacher" / "latest.pt")
    assert check_run_checkpoints(run, cfg, "resume") == [
        f"[teacher] checked {run / 'teacher' / 'latest.pt'}: iteration 2"
    ]
    save_atomic(_payload(seed=7), run / "teacher" / "latest.pt")
    with pytest.raises(ConfigError, match=r"another config .*seed: 7 -> 0"):
        check_run_checkpoints(run, cfg, "resume")
    bad = _payload()
    bad["iteration"] = "../../x"
    save_atomic(bad, run / "teacher" / "latest.pt")
    out = _train(capfd, f"resume={run}")
    _one_line(out, f"resume={run}: {run / 'teacher' / 'latest.pt'}: its iteration '../../x'")
    stage_student = _payload(**{"reward.label": "${oc.env:HOME}"})
    save_atomic(stage_student, tmp_path / "t.pt")
    _one_line(
        _train(capfd, "compute=smoke", "stage=student", f"teacher_ckpt={tmp_path / 't.pt'}"),
        "reward.label holds a '${...}'",
    )


# ------------------------------------------------------------------ 5. no writes through links


def test_a_run_file_is_never_written_through_a_link(tmp_path):
    elsewhere = tmp_path / "elsewhere.csv"
    run = tmp_path / "run"
    run.mkdir()
    os.symlink(elsewhere, run / "eval.csv")  # dangling: append would create elsewhere.csv
    with pytest.raises(ConfigError, match="is a symbolic link"):
        append_row(run / "eval.csv", METRIC_COLUMNS, {"stage": "teacher"})
    assert not elsewhere.exists()
    elsewhere.write_text("keep\n")
    with pytest.raises(ConfigError, match="is a symbolic link"):
        append_row(run / "eval.csv", METRIC_COLUMNS, {"stage": "teacher"})
    assert elsewhere.read_text() == "keep\n"
    append_row(run / "metrics.csv", METRIC_COLUMNS, {"stage": "teacher", "iteration": 1})
    assert (run / "metrics.csv").read_text().count("\n") == 2


@pytest.mark.parametrize("name", ["env.log", "metrics.csv", "teacher", "student/latest.pt"])
def test_a_link_in_a_run_directory_is_refused(tmp_path, name):
    run = _saved_run(tmp_path)
    (run / "student").mkdir()
    os.symlink(tmp_path / "target", run / name)
    with pytest.raises(ConfigError, match="is a symbolic link"):
        refuse_links(run, "resume")


def test_cli_resume_of_a_run_with_a_link_is_refused(tmp_path, capfd):
    run = _saved_run(tmp_path)
    os.symlink(tmp_path / "x.log", run / "env.log")
    _one_line(_train(capfd, f"resume={run}"), f"{run / 'env.log'} is a symbolic link")
    assert not (tmp_path / "x.log").exists()


# ------------------------------------------------------------------ 6. preemption is visible


@pytest.fixture
def handler():
    assert preemption.install()
    yield
    preemption.uninstall()


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGUSR2])
def test_a_signal_stops_after_the_iteration_is_checkpointed(tmp_path, handler, sig):
    saved = []

    def save() -> Path:
        saved.append(3)
        return tmp_path / "model_000003.pt"

    preemption.stop_if_requested("teacher", 2, save)  # no signal yet: goes on
    assert saved == []
    os.kill(os.getpid(), sig)
    with pytest.raises(preemption.Preempted) as stop:
        preemption.stop_if_requested("teacher", 3, save)
    assert saved == [3] and stop.value.checkpoint == tmp_path / "model_000003.pt"
    status: dict = {}
    with pytest.raises(SystemExit) as code:
        preemption.exit_preempted(stop.value, lambda state, **kw: status.update(state=state, **kw))
    assert code.value.code == 128 + sig
    assert status == {
        "state": "preempted",
        "stage": "teacher",
        "iteration": 3,
        "checkpoint": str(tmp_path / "model_000003.pt"),
        "signal": signal.Signals(sig).name,
    }


def test_a_save_point_is_not_saved_twice_and_a_second_signal_stops_at_once(handler):
    os.kill(os.getpid(), signal.SIGTERM)
    with pytest.raises(preemption.Preempted) as stop:
        preemption.stop_if_requested("student", 4, None, Path("latest.pt"))
    assert stop.value.checkpoint == Path("latest.pt") and stop.value.iteration == 4
    with pytest.raises(preemption.Preempted) as again:
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(1)  # the handler raises here
    assert again.value.iteration is None and "stopped at once" in again.value.line()


@pytest.mark.slow
def test_sigterm_leaves_status_preempted_and_a_resume_finishes(tmp_path):
    """A real smoke run, SIGTERM during the teacher: exit 143, status preempted naming the
    checkpointed iteration; the resume ends done."""
    run = tmp_path / "run"
    proc = subprocess.Popen(
        [sys.executable, "-m", "march.train", "compute=smoke", "teacher.max_iterations=6",
         "teacher.save_interval=3", f"hydra.run.dir={run}"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    for line in proc.stdout:
        if line.startswith("[teacher] it 1/"):
            proc.send_signal(signal.SIGTERM)
            break
    rest = proc.stdout.read()
    assert proc.wait(timeout=300) == 128 + signal.SIGTERM, rest[-3000:]
    status = json.loads((run / "status.json").read_text())
    assert status["state"] == "preempted" and status["signal"] == "SIGTERM", status
    assert 2 <= status["iteration"] < 6 and "[preempted] SIGTERM" in rest
    assert (run / "teacher" / f"model_{status['iteration']:06d}.pt").is_file()
    done = train_cli(f"resume={run}", timeout=600)  # a real run, to its end
    assert done.returncode == 0, done.stderr[-3000:]
    assert f"resuming from {run / 'teacher' / 'latest.pt'} at iteration" in done.stdout
    assert json.loads((run / "status.json").read_text())["state"] == "done"
    assert OmegaConf.load(run / "config.yaml").seed == 0
