"""One door to the disk (issue 47, SPEC section 9): every tool reads a checkpoint through
``march.store.gate`` and gets the same one-line refusal; a file never makes march import a
module; weights are checked against their config before any env; links, sizes and gzip bombs
are refused before anything is allocated; run directories cannot collide; status tells the
truth; the saved-vs-new config rules are one copy.

Crafted checkpoints are copies of the session's smoke run (tests/conftest.py), changed in one
entry each.
"""

from __future__ import annotations

import functools
import gzip
import hashlib
import json
import os
import socket
import subprocess
import sys
import tracemalloc
from dataclasses import asdict
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf
from tool_in_process import run_tool

from march.config import ConfigError
from march.config.cli import load
from march.store import run_lock
from march.store.bounded_read import FileRefused, gunzip_bounded, parse_json_strict
from march.store.checkpoint import CheckpointError, load_checkpoint, save_atomic
from march.store.gate import check_weights, read_checkpoint
from march.store.provenance import apply_checkpoint_config
from march.store.resume_rules import adopt_config, load_saved_config
from march.store.status import read_status, write_status

ROOT = Path(__file__).resolve().parent.parent
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        env=ENV,
    )


def _tool(capfd, module: str, *args: str) -> subprocess.CompletedProcess:
    """``python -m <module> <args>`` in this process (tests/tool_in_process.py): what a tool
    says on refusing a file, without a subprocess's ~2 s of CPU. ``this`` (the module a crafted
    config names) is taken out of ``sys.modules`` first, so that importing it would print its
    poem again, and the run must leave it unimported."""
    sys.modules.pop("this", None)
    out = run_tool(capfd, module, *args)
    assert "this" not in sys.modules, f"{module} imported the module a file named"
    return out


def _crafted(smoke_run: Path, folder: Path, kind: str = "student", **entries) -> Path:
    """The smoke run's checkpoint with ``entries`` replaced (``config.<key>`` in its config)."""
    payload = load_checkpoint(smoke_run / kind / "latest.pt", kind)
    for key, value in entries.items():
        if key.startswith("config__"):
            payload["config"][key.removeprefix("config__")] = value
        else:
            payload[key] = value
    folder.mkdir(parents=True, exist_ok=True)
    save_atomic(payload, folder / "latest.pt")
    return folder / "latest.pt"


# --- 1. one gate, the same refusal from every tool ---------------------------------------------


CRAFTED = {
    "iteration": ({"iteration": "../../x"}, "its iteration '../../x' is not a whole number"),
    "interpolation": (
        {"config__reward": {"name": "${oc.env:HOME}"}},
        "its config key reward.name holds a '${...}' interpolation or resolver",
    ),
    "module": (
        {"config__extra_modules": ["this"]},
        "its config names module 'this' (extra_modules), which you did not name",
    ),
}


@pytest.mark.parametrize(
    "fault",
    # One fault in the default suite proves every tool reads through the gate; the other two
    # (the same 6 tool launches each, ~45 s on 2 cores) run with the slow tests (make test-all).
    [f if f == "iteration" else pytest.param(f, marks=pytest.mark.slow) for f in sorted(CRAFTED)],
)
def test_every_tool_gets_the_same_refusal_from_the_gate(smoke_run, tmp_path, fault, capfd):
    """export, play, train stage=eval, train stage=student, march.audit rewards and a resume, on ONE crafted
    checkpoint: the same line (after the label naming the file), exit 2, nothing run. Each
    tool's command line runs in this process (``_tool``): six subprocesses cost ~40 s."""
    entries, needle = CRAFTED[fault]
    ckpt = _crafted(smoke_run, tmp_path / "ck", **entries)
    teacher = _crafted(smoke_run, tmp_path / "tk", "teacher", **entries)
    label = f"student_ckpt={ckpt}"
    _run = functools.partial(_tool, capfd)
    runs = {
        "export": (_run("march.export", f"student_ckpt={ckpt}", f"out={tmp_path / 'x'}"), label),
        "play": (_run("march.play", f"student_ckpt={ckpt}", f"out={tmp_path / 'v.mp4'}"), label),
        "train eval": (
            _run(
                "march.train",
                "compute=smoke",
                "stage=eval",
                f"student_ckpt={ckpt}",
                f"hydra.run.dir={tmp_path / 'e'}",
            ),
            label,
        ),
        "train student": (
            _run(
                "march.train",
                "compute=smoke",
                "stage=student",
                f"teacher_ckpt={teacher}",
                f"hydra.run.dir={tmp_path / 's'}",
            ),
            f"teacher_ckpt={teacher}",
        ),
        "audit rewards": (
            _run(
                "march.audit",
                "rewards",
                "compute=smoke",
                f"teacher_ckpt={teacher}",
                f"out={tmp_path / 'a.json'}",
            ),
            f"teacher_ckpt={teacher}",
        ),
    }
    # A resume of a run whose student checkpoint is the crafted one.
    run = tmp_path / "run"
    run.mkdir()
    for name in ("config.yaml", "metrics.csv"):
        (run / name).write_bytes((smoke_run / name).read_bytes())
    (run / "teacher").mkdir()
    (run / "teacher" / "latest.pt").write_bytes((smoke_run / "teacher" / "latest.pt").read_bytes())
    (run / "student").mkdir()
    (run / "student" / "latest.pt").write_bytes(ckpt.read_bytes())
    runs["resume"] = (
        _run("march.train", f"resume={run}"),
        f"resume={run}: {run}/student/latest.pt",
    )
    reasons = set()
    for tool, (out, where) in runs.items():
        lines = [ln for ln in out.stderr.splitlines() if ln.startswith("error: ")]
        assert out.returncode == 2 and len(lines) == 1, (tool, out.stdout[-800:], out.stderr[-800:])
        assert lines[0].startswith(f"error: {where}: "), (tool, lines[0])
        assert needle in lines[0], (tool, lines[0])
        reasons.add(lines[0].removeprefix(f"error: {where}: "))
        assert "Beautiful is better than ugly" not in out.stdout + out.stderr, tool  # `this`
        assert "[env]" not in out.stdout and "march.train  stage" not in out.stdout, tool
    assert len(reasons) == 1, reasons  # one gate: one message


# --- weights against config, before any env ------------------------------------------------


@pytest.mark.parametrize("kind", ["teacher", "student"])
def test_every_tensor_of_a_checkpoint_is_checked_against_its_config(smoke_run, kind):
    """Each tensor in turn made one row longer, dropped, or joined by a stranger: refused,
    naming it; the untouched checkpoint passes."""
    payload, cfg = read_checkpoint(str(smoke_run / kind / "latest.pt"), kind, [])
    key = "actor_state_dict" if kind == "teacher" else "student_state_dict"
    weights = payload[key]
    for name, tensor in weights.items():
        for fault in ("grown", "missing"):
            bad = dict(weights)
            if fault == "missing":
                del bad[name]
            else:
                shape = list(tensor.shape) or [1]
                shape[0] += 1
                bad[name] = torch.zeros(shape)
            with pytest.raises(ConfigError) as err:
                check_weights({**payload, key: bad}, kind, "L", cfg)
            assert name in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(ConfigError, match="holds stranger"):
        check_weights({**payload, key: {**weights, "stranger": torch.zeros(1)}}, kind, "L", cfg)
    check_weights(payload, kind, "L", cfg)


def test_weights_that_disagree_with_their_config_are_refused_before_any_env(
    smoke_run, tmp_path, capfd
):
    payload = load_checkpoint(smoke_run / "student" / "latest.pt", "student")
    payload["config"]["student"]["d_model"] = 2 * payload["config"]["student"]["d_model"]
    save_atomic(payload, tmp_path / "s.pt")
    out = _tool(
        capfd,
        "march.train",
        "compute=smoke",
        "stage=eval",
        f"student_ckpt={tmp_path / 's.pt'}",
        f"hydra.run.dir={tmp_path / 'e'}",
    )
    assert out.returncode == 2, out.stdout[-1000:]
    # no banner, no env built: stdout holds at most PyOpenGL's import note
    assert [ln for ln in out.stdout.splitlines() if "OpenGL" not in ln] == [], out.stdout[-1000:]
    (line,) = [ln for ln in out.stderr.splitlines() if ln.startswith("error:")]
    assert "its weights do not fit its config" in line and "has shape" in line, line


# --- files: links, sizes, bounded inflation, strict JSON -----------------------------------


def test_a_linked_checkpoint_is_refused_and_export_writes_nothing_outside(
    smoke_run, tmp_path, capfd
):
    _run = functools.partial(_tool, capfd)
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "latest.pt").write_bytes((smoke_run / "student" / "latest.pt").read_bytes())
    run = tmp_path / "run" / "student"
    run.mkdir(parents=True)
    (run / "latest.pt").symlink_to(outside / "latest.pt")
    out = _run("march.export", f"student_ckpt={run / 'latest.pt'}")
    assert out.returncode == 2 and "is a symbolic link" in out.stderr, out.stderr[-500:]
    # A linked folder: the checkpoint itself is a file, but the default out= would land outside.
    (tmp_path / "run2").mkdir()
    (tmp_path / "run2" / "student").symlink_to(outside)
    out = _run("march.export", f"student_ckpt={tmp_path / 'run2' / 'student' / 'latest.pt'}")
    assert out.returncode == 2 and "reached through a symbolic link" in out.stderr, out.stderr
    assert sorted(p.name for p in outside.iterdir()) == ["latest.pt"]  # nothing written there


def test_a_checkpoint_over_the_size_bound_is_refused_before_it_is_read(
    smoke_run, tmp_path, monkeypatch
):
    import march.store.checkpoint as ck

    monkeypatch.setattr(ck, "MAX_CHECKPOINT_BYTES", 1000)
    monkeypatch.setattr(torch, "load", lambda *a, **k: pytest.fail("read past the bound"))
    with pytest.raises(CheckpointError, match="more than the 1000"):
        load_checkpoint(smoke_run / "student" / "latest.pt", "student")


def test_a_gzip_bomb_is_refused_within_its_bound(tmp_path):
    """100 MB of zeros packed into ~100 KB: refused at 16 x its packed size (1.6 MB), and the
    inflation never holds more than that plus a 1 MB piece or two."""
    from march.sim2sim.deploy_bundle import Bundle, UsageError

    packed = gzip.compress(bytes(100 << 20), compresslevel=9)
    (tmp_path / "s.mjb.gz").write_bytes(packed)
    spec = {
        "courses": {"stones": {"scene": "s.mjb.gz", "sha256": hashlib.sha256(packed).hexdigest()}}
    }
    tracemalloc.start()
    with pytest.raises(UsageError, match="inflates to more than"):
        Bundle(tmp_path / "x.onnx", spec).scene("stones")
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    # unbounded, gzip.decompress held all 100 MB; here: the bound plus a piece or two
    assert len(packed) < 200_000 and peak < 8 << 20, (len(packed), peak)
    data = os.urandom(3 << 20)
    assert gunzip_bounded(gzip.compress(data), 4 << 20, "x") == data


def test_a_50_mb_deploy_json_is_refused_before_it_is_read(tmp_path):
    from march.sim2sim.deploy_bundle import Bundle, UsageError

    (tmp_path / "student.onnx").write_bytes(b"onnx")
    with (tmp_path / "student.deploy.json").open("wb") as f:
        f.write(b'{"format": 3, "pad": "' + b"x" * (50 << 20) + b'"}')
    with pytest.raises(UsageError, match=r"is 524288\d+ bytes, more than the 16777216"):
        Bundle.load(tmp_path / "student.onnx")


@pytest.mark.parametrize(
    "text,needle",
    [
        ('{"a": 1, "a": 2}', "the key 'a' is given twice"),
        ('{"kp": NaN}', "NaN is not a JSON number"),
        ('{"kp": -Infinity}', "-Infinity is not a JSON number"),
        ("[" * 200 + "]" * 200, "nested deeper than 64"),
        ('{"a": 1} x', "not readable JSON"),
    ],
)
def test_deploy_json_is_parsed_strictly(text, needle):
    with pytest.raises(FileRefused, match=needle):
        parse_json_strict(text.encode(), "deploy.json")


# --- 2. nothing imported because a file names it -------------------------------------------


def _plant_module(tmp_path: Path, monkeypatch) -> str:
    name = "march_planted_by_a_file"
    (tmp_path / f"{name}.py").write_text(
        f"import pathlib\npathlib.Path({str(tmp_path / 'imported')!r}).write_text('ran')\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    sys.modules.pop(name, None)
    return name


def test_a_module_a_checkpoint_names_is_imported_only_when_the_user_names_it(tmp_path, monkeypatch):
    name = _plant_module(tmp_path, monkeypatch)
    cfg = load(["compute=smoke"])
    saved = asdict(cfg)
    saved["extra_modules"] = [name]
    payload = {"kind": "student", "config": saved}
    with pytest.raises(ConfigError) as err:
        apply_checkpoint_config(cfg, payload, [], "s.pt", "student")
    assert str(err.value).startswith(f"student_ckpt=s.pt: its config names module '{name}'")
    assert f"extra_modules=[{name}]" in str(err.value)
    assert not (tmp_path / "imported").exists() and name not in sys.modules
    # Named by the user too (their extra_modules, imported by the tool): accepted.
    mine = load(["compute=smoke", f"extra_modules=[{name}]"])
    assert (tmp_path / "imported").exists()
    apply_checkpoint_config(mine, payload, [], "s.pt", "student")


def test_a_module_a_run_config_names_is_imported_only_when_the_user_names_it(tmp_path, monkeypatch):
    name = _plant_module(tmp_path, monkeypatch)
    cfg = load(["compute=smoke"])
    run = tmp_path / "run"
    run.mkdir()
    saved = OmegaConf.structured(cfg)
    saved.extra_modules = [name]
    (run / "config.yaml").write_text(OmegaConf.to_yaml(saved))
    with pytest.raises(ConfigError, match=f"names module '{name}'"):
        load_saved_config(run, "resume", named=[])
    assert not (tmp_path / "imported").exists()
    assert load_saved_config(run, "resume", named=[name]).extra_modules == [name]


# --- 1. the rules between a saved config and a new one: one copy -----------------------------


def test_a_new_run_in_a_run_directory_follows_resumes_rules(tmp_path):
    """teacher.max_iterations=3 in a finished 2+2 run: refused as resume= refuses it."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text(
        OmegaConf.to_yaml(OmegaConf.structured(load(["compute=smoke"])))
    )
    (run / "student").mkdir()
    (run / "student" / "model_000002.pt").write_bytes(b"")
    more = load(["compute=smoke", "teacher.max_iterations=3"])
    with pytest.raises(ConfigError) as err:
        adopt_config(run, more)
    assert str(err.value) == (
        f"hydra.run.dir={run}: teacher.max_iterations cannot change once the distillation has "
        "started (student/ holds checkpoints of a student of the current teacher)"
    )
    cfg, _ = adopt_config(run, load(["compute=smoke", "distill.max_iterations=3"]))
    assert cfg.distill.max_iterations == 3


# --- 4. run directories that cannot collide -------------------------------------------------


def test_run_directories_carry_the_seed_and_a_unique_part():
    code = (
        "import hydra; from march.config.cli import CONF_DIR\n"
        "with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base='1.3'):\n"
        "    c = hydra.compose(config_name='config', overrides=['compute=smoke', 'seed=4'],"
        " return_hydra_config=True)\n"
        "print(c.hydra.run.dir); print(c.hydra.run.dir)\n"
    )
    dirs = [
        subprocess.run(
            [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, env=ENV
        ).stdout.split()
        for _ in range(2)
    ]
    assert dirs[0][0] == dirs[0][1]  # stable within a process
    assert dirs[0][0] != dirs[1][0]  # two processes in the same second: two directories
    assert all("_seed4_" in d[0] for d in dirs), dirs


def test_a_refused_directory_says_whose_it_is(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    cfg = OmegaConf.structured(load(["compute=smoke", "seed=3"]))
    (run / "config.yaml").write_text(OmegaConf.to_yaml(cfg))
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time; from march.store import run_lock; "
            "run_lock.acquire(sys.argv[1]); print('held', flush=True); time.sleep(60)",
            str(run),
        ],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        text=True,
        env=ENV,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(run_lock.RunLocked) as err:
            run_lock.acquire(run, "hydra.run.dir")
        text = str(err.value)
        assert f"pid {holder.pid}" in text and "another run's directory (seed 3, stage all)" in text
        assert "give this run its own hydra.run.dir" in text and "wait for it" not in text
        with pytest.raises(run_lock.RunLocked, match="wait for it to end"):
            run_lock.acquire(run, "resume")  # the user's own run: wait
    finally:
        holder.kill()
        holder.wait()


# --- 5. status that tells the truth; takeover only on the same host ------------------------


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_a_running_status_whose_pid_is_gone_reads_killed(tmp_path):
    host = socket.gethostname()
    dead = _dead_pid()
    write_status(tmp_path, "running", stage="all", pid=dead, host=host)
    status = read_status(tmp_path)
    assert status["state"] == "killed" and status["recorded"] == "running"
    assert f"pid {dead} is gone" in status["note"]
    out = _run("march.inspect", "run", str(tmp_path))
    assert json.loads(out.stdout)["status"]["state"] == "killed", out.stderr[-500:]
    sys.path.insert(0, str(ROOT))
    from analysis.rundirs import load_run

    assert load_run(tmp_path).state == "killed"
    write_status(tmp_path, "running", stage="all", pid=os.getpid(), host=host)
    assert read_status(tmp_path)["state"] == "running"  # alive
    write_status(tmp_path, "running", stage="all", pid=dead, host="another-node")
    assert read_status(tmp_path)["state"] == "running"  # not this host's to judge


def test_a_stale_lock_of_another_host_is_not_taken_over(tmp_path, monkeypatch):
    lock = tmp_path / "run.lock"
    lock.write_text(json.dumps({"pid": _dead_pid(), "host": "node-elsewhere", "since": 0}))
    monkeypatch.delenv(run_lock.TAKEOVER_ENV, raising=False)
    with pytest.raises(run_lock.RunLocked) as err:
        run_lock.acquire(tmp_path, "resume")
    assert "on host node-elsewhere" in str(err.value) and "another host than this" in str(err.value)
    assert "MARCH_LOCK_TAKEOVER=1" in str(err.value) and "\n" not in str(err.value)
    assert json.loads(lock.read_text())["host"] == "node-elsewhere"  # nothing written
    monkeypatch.setenv(run_lock.TAKEOVER_ENV, "1")
    held = run_lock.acquire(tmp_path, "resume")
    try:
        assert held.stale["host"] == "node-elsewhere"
    finally:
        held.release()
    # The same host, holder gone: taken over as before.
    monkeypatch.delenv(run_lock.TAKEOVER_ENV)
    lock.write_text(json.dumps({"pid": _dead_pid(), "host": socket.gethostname(), "since": 0}))
    run_lock.acquire(tmp_path, "resume").release()
