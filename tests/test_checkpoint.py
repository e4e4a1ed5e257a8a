"""Checkpoints are plain data: a crafted file runs nothing, real ones round-trip (issue 15), and
they load onto any device with RNG states that resume (issue 11, item 4).

The crafted payload's side effect is creating a file in the test's tmp dir; a control load with
``weights_only=False`` proves the payload is live (it does create its file there).
"""

from __future__ import annotations

import ast
import copy
import os
import re
import subprocess
import sys
import types
from collections import OrderedDict
from pathlib import Path

import numpy as np
import pytest
import torch

from march.store.checkpoint import (
    CheckpointError,
    load_checkpoint,
    non_plain,
    save_checkpoint,
    to_plain,
)

ROOT = Path(__file__).resolve().parent.parent


class CreatesFile:
    """Unpickling this calls ``open(path, "w")``: the side effect of a crafted checkpoint."""

    def __init__(self, path: Path) -> None:
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


def crafted(path: Path, target: Path, kind: str = "teacher", legacy: bool = False) -> Path:
    """A file shaped like a march checkpoint whose unpickling would create ``target``."""
    payload = {"kind": kind, "iteration": 1, "layout": {}, "x": CreatesFile(target)}
    torch.save(payload, path, _use_new_zipfile_serialization=not legacy)
    return path


def one_line_error(path: Path, kind: str = "teacher", device: str = "cpu") -> str:
    with pytest.raises(CheckpointError) as info:
        load_checkpoint(path, kind, device)
    msg = str(info.value)
    assert "\n" not in msg and msg.startswith(f"{kind}_ckpt={path}: "), msg
    assert len(msg) - len(str(path)) < 320, msg
    return msg


def small_payload(kind: str = "student") -> dict:
    """The shape of a march payload: a real module's state, Adam's state, RNG states, config."""
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Linear(5, 4), torch.nn.LayerNorm(4), torch.nn.Linear(4, 3))
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    for _ in range(3):
        opt.zero_grad()
        net(torch.randn(8, 5)).square().mean().backward()
        opt.step()
    return {
        "kind": kind,
        "iteration": 3,
        "wall_s": 1.5,
        "config": {"seed": 0, "student": {"variant": "full", "dims": (64, 32)}, "none": None},
        "layout": {"image_hw": [24, 32]},
        "student_state_dict": net.state_dict(),
        "optimizer_state_dict": opt.state_dict(),
        "generator": torch.Generator().manual_seed(7).get_state(),
        "rng": torch.get_rng_state(),
    }


def assert_same(a, b, where="payload"):
    assert type(a) is type(b), where
    if isinstance(a, dict):
        assert list(a) == list(b), where
        for k in a:
            assert_same(a[k], b[k], f"{where}[{k!r}]")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same(x, y, f"{where}[{i}]")
    elif isinstance(a, torch.Tensor):
        assert a.dtype == b.dtype and torch.equal(a.cpu(), b.cpu()), where
    else:
        assert a == b, where


# ---------------------------------------------------------------------------------------------
# Refusals: one line each, nothing in the file runs


@pytest.mark.parametrize("legacy", [False, True], ids=["zip", "legacy"])
def test_crafted_pickle_is_refused_and_runs_nothing(tmp_path, legacy):
    control = crafted(tmp_path / "control.pt", tmp_path / "control_ran", legacy=legacy)
    torch.load(control, weights_only=False)  # the unsafe read, as before issue 15
    assert (tmp_path / "control_ran").exists(), "the crafted payload is not live"

    target = tmp_path / "ran"
    path = crafted(tmp_path / "crafted.pt", target, legacy=legacy)
    for device in ("cpu", "meta"):
        msg = one_line_error(path, "teacher", device)
        assert "refused" in msg and "io.open" in msg and "nothing in the file was run" in msg
    assert not target.exists()


@pytest.mark.parametrize(
    "obj, named",
    [
        (torch.nn.Linear(2, 2), "torch.nn.modules.linear.Linear"),  # a whole module object
        (np.zeros(3), "numpy"),
        (Path("/tmp"), "pathlib"),
        (torch.Generator(), "Generator"),  # a generator object instead of its state
    ],
    ids=["module", "numpy", "path", "generator"],
)
def test_non_plain_objects_are_refused_by_name(tmp_path, obj, named):
    path = tmp_path / "x.pt"
    torch.save({"kind": "student", "x": obj}, path)
    msg = one_line_error(path, "student")
    assert "refused" in msg and named in msg


def test_types_other_libraries_allow_list_are_refused(tmp_path):
    # tensordict allow-lists TensorDict for weights_only loads; a march checkpoint never holds one.
    from tensordict import TensorDict

    path = tmp_path / "td.pt"
    torch.save({"kind": "teacher", "obs": TensorDict({"a": torch.ones(2)}, batch_size=[2])}, path)
    msg = one_line_error(path, "teacher")
    assert "TensorDict at payload['obs']" in msg and "not plain data" in msg


def test_truncated_random_and_empty_files_give_one_line(tmp_path):
    save_checkpoint(small_payload(), tmp_path, 3)
    good = tmp_path / "latest.pt"
    data = good.read_bytes()
    rng = np.random.default_rng(0)
    cases = {
        "truncated.pt": data[: len(data) // 2],
        "head.pt": data[:100],
        "random.pt": rng.bytes(4096),
        "empty.pt": b"",
        "text.pt": b"not a checkpoint\n",
    }
    for name, blob in cases.items():
        (tmp_path / name).write_bytes(blob)
        msg = one_line_error(tmp_path / name, "student")
        assert "not a readable checkpoint" in msg, (name, msg)


def test_wrong_kind_missing_file_and_bad_rng_state(tmp_path):
    torch.save([1, 2, 3], tmp_path / "list.pt")
    assert "'list' checkpoint, not a student" in one_line_error(tmp_path / "list.pt", "student")
    assert "no such file" in one_line_error(tmp_path / "nope.pt", "student")
    payload = small_payload()
    payload["rng"] = torch.zeros(5)  # float, not a byte state
    torch.save(payload, tmp_path / "rng.pt")
    assert "'rng' is not a torch RNG state" in one_line_error(tmp_path / "rng.pt", "student")


def test_save_refuses_what_load_would_refuse(tmp_path):
    payload = small_payload()
    payload["where"] = Path("outputs/run")
    with pytest.raises(TypeError, match=r"PosixPath at payload\['where'\]|Path at payload"):
        save_checkpoint(payload, tmp_path, 1)
    assert not list(tmp_path.glob("*.pt"))


def test_to_plain_makes_an_older_payload_loadable(tmp_path):
    """The README's re-save snippet: an old file with numpy, paths and a Generator object."""
    old = small_payload()
    old.update(
        curve=np.arange(4, dtype=np.float32),
        best=np.float64(2.5),
        teacher_ckpt=Path("outputs/run/teacher/latest.pt"),
        generator=torch.Generator().manual_seed(7),
        layout=types.MappingProxyType({"image_hw": (24, 32)}),
    )
    assert non_plain(old) is not None
    new = to_plain(old)
    assert non_plain(new) is None
    save_checkpoint(new, tmp_path, 3)
    back = load_checkpoint(tmp_path / "latest.pt", "student")
    assert torch.equal(back["curve"], torch.arange(4, dtype=torch.float32))
    assert back["best"] == 2.5 and back["teacher_ckpt"] == "outputs/run/teacher/latest.pt"
    assert back["layout"] == {"image_hw": (24, 32)}
    g = torch.Generator()
    g.set_state(back["generator"])
    assert torch.equal(
        torch.rand(3, generator=g), torch.rand(3, generator=torch.Generator().manual_seed(7))
    )
    with pytest.raises(TypeError, match="is not plain data"):
        to_plain({"x": object()})


def _unsafe_reads(tree: ast.AST) -> list[tuple[int, str]]:
    """Calls and imports that can unpickle (or construct Python objects from YAML)."""
    names = {"pickle", "dill", "cloudpickle", "joblib", "shelve", "marshal"}
    found = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            mods = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module]
            imported = [a.name for a in node.names]
            if any((m or "").split(".")[0] in names for m in mods) or (
                isinstance(node, ast.ImportFrom) and node.module == "torch" and "load" in imported
            ):
                found.append((node.lineno, ast.unparse(node)))
        if not isinstance(node, ast.Call):
            continue
        func = ast.unparse(node.func)
        kw = {k.arg: ast.unparse(k.value) for k in node.keywords}
        if (
            func in ("torch.load", "torch.jit.load", "yaml.unsafe_load", "yaml.full_load")
            or func.endswith(("Unpickler", "pickle.load", "pickle.loads"))
            or (func == "yaml.load" and "Safe" not in kw.get("Loader", ""))
            or (func.endswith("np.load") and kw.get("allow_pickle") == "True")
        ):
            found.append((node.lineno, ast.unparse(node)))
    return found


def test_every_checkpoint_read_goes_through_load_checkpoint():
    """No module unpickles anything except load_checkpoint, whose one read is weights-only."""
    sources = [
        p
        for top in ("march", "analysis", "scripts", "hydra_plugins")
        for p in sorted((ROOT / top).rglob("*.py"))
    ]
    assert len(sources) > 20
    reads = {
        f"{src.relative_to(ROOT)}:{line}": code
        for src in sources
        for line, code in _unsafe_reads(ast.parse(src.read_text()))
    }
    elsewhere = [w for w in reads if not w.startswith("march/store/checkpoint.py:")]
    assert elsewhere == [], reads
    # checkpoint.py imports pickle for its UnpicklingError; its one read is weights-only
    calls = [code for code in reads.values() if not code.startswith("import ")]
    assert calls == ["torch.load(f, map_location='cpu', weights_only=True)"], reads
    # the scanner finds what it must refuse
    bad = "import pickle\nfrom torch import load\ntorch.load(f)\nyaml.load(s, Loader=yaml.Loader)"
    assert len(_unsafe_reads(ast.parse(bad))) == 4


# ---------------------------------------------------------------------------------------------
# Device independence (issue 11, item 4)


@pytest.mark.parametrize("device", ["cpu", "meta"])
def test_tensors_go_to_the_device_rng_states_stay_on_cpu(tmp_path, device):
    payload = small_payload()
    save_checkpoint(payload, tmp_path, 3)
    back = load_checkpoint(tmp_path / "latest.pt", "student", device)
    for v in back["student_state_dict"].values():
        assert v.device.type == device
    state = back["optimizer_state_dict"]["state"]
    for s in state.values():
        assert s["exp_avg"].device.type == device and s["exp_avg_sq"].device.type == device
        assert s["step"].device.type == "cpu" and float(s["step"]) == 3.0  # as torch.optim keeps it
    # state_dict's module-version metadata survives (load_state_dict reads it)
    assert back["student_state_dict"]._metadata == payload["student_state_dict"]._metadata
    for key in ("rng", "generator"):
        assert back[key].device.type == "cpu" and back[key].dtype == torch.uint8
        assert torch.equal(back[key], payload[key])
    # ... and they resume: the same draws as from the saved states
    before = torch.get_rng_state()
    try:
        torch.set_rng_state(back["rng"])
        a = torch.rand(4)
        torch.set_rng_state(payload["rng"])
        assert torch.equal(a, torch.rand(4))
    finally:
        torch.set_rng_state(before)
    g = torch.Generator()
    g.set_state(back["generator"])
    assert torch.equal(
        torch.rand(4, generator=g), torch.rand(4, generator=torch.Generator().manual_seed(7))
    )
    if device == "cpu":
        assert_same(back, payload)


# ---------------------------------------------------------------------------------------------
# The CLI: a crafted teacher_ckpt fails before any env is built


def test_train_cli_refuses_crafted_teacher_ckpt(tmp_path):
    target = tmp_path / "ran"
    path = crafted(tmp_path / "crafted.pt", target)
    run_dir = tmp_path / "run"
    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "march.train",
            "compute=smoke",
            "stage=student",
            f"teacher_ckpt={path}",
            f"hydra.run.dir={run_dir}",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "WANDB_MODE": "offline"},
    )
    assert res.returncode != 0
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith(f"error: teacher_ckpt={path}: refused") and "io.open" in lines[0]
    assert not target.exists()
    assert not (run_dir / "env.log").exists()  # no env was built


# ---------------------------------------------------------------------------------------------
# Real checkpoints from the session's smoke pipeline: save, load, resume, export


@pytest.mark.sim
@pytest.mark.parametrize("kind", ["teacher", "student"])
def test_real_checkpoint_round_trips(smoke_run, tmp_path, kind):
    src = smoke_run / kind / "latest.pt"
    payload = load_checkpoint(src, kind)
    assert non_plain(payload) is None
    save_checkpoint(payload, tmp_path, payload["iteration"])
    again = load_checkpoint(tmp_path / "latest.pt", kind)
    assert_same(payload, again)
    assert (tmp_path / f"model_{payload['iteration']:06d}.pt").is_file()


@pytest.mark.sim
@pytest.mark.parametrize("kind", ["teacher", "student"])
def test_real_checkpoint_loads_on_meta_and_its_rng_resumes(smoke_run, kind):
    payload = load_checkpoint(smoke_run / kind / "latest.pt", kind, "meta")
    weights = payload[f"{'actor' if kind == 'teacher' else 'student'}_state_dict"]
    assert weights and all(v.is_meta for v in weights.values())
    assert all(
        v.is_meta
        for s in payload["optimizer_state_dict"]["state"].values()
        for k, v in s.items()
        if k != "step"
    )
    before = torch.get_rng_state()
    try:
        torch.set_rng_state(payload["rng"])  # raised on a meta/CUDA-mapped state before
        assert torch.equal(torch.get_rng_state(), payload["rng"])
    finally:
        torch.set_rng_state(before)
    if kind == "student":
        g = torch.Generator()
        g.set_state(payload["generator"])
        assert torch.equal(g.get_state(), payload["generator"])


@pytest.mark.sim
def test_real_teacher_resumes(smoke_run):
    """What TeacherRunner.try_resume does, on rsl-rl's PPO built from the checkpoint's own cfg."""
    from rsl_rl.algorithms import PPO
    from tensordict import TensorDict

    payload = load_checkpoint(smoke_run / "teacher" / "latest.pt", "teacher")
    dims = {
        g: payload[f"{g}_state_dict"]["obs_normalizer._mean"].shape[-1] for g in ("actor", "critic")
    }
    obs = TensorDict({g: torch.zeros(2, d) for g, d in dims.items()}, batch_size=[2])
    # PPO reads only these two sizes from its env argument when it builds the networks
    sizes = types.SimpleNamespace(num_actions=payload["layout"]["num_actions"], num_envs=2)
    alg = PPO.construct_algorithm(obs, sizes, copy.deepcopy(payload["ppo"]), "cpu")
    alg.load(payload, None, strict=True)
    saved = alg.save()
    for key in ("actor_state_dict", "critic_state_dict", "optimizer_state_dict"):
        assert_same(saved[key], payload[key], key)


@pytest.mark.sim
def test_real_student_resumes(smoke_run):
    """What DistillRunner.try_resume does: weights, optimizer, generator."""
    from march.config.cli import load
    from march.learn.distill import build_student

    payload = load_checkpoint(smoke_run / "student" / "latest.pt", "student")
    cfg = load(["compute=smoke"])
    student = build_student(cfg, payload["layout"], "cpu")
    student.load_state_dict(payload["student_state_dict"])
    opt = torch.optim.Adam(student.parameters(), lr=cfg.distill.learning_rate)
    opt.load_state_dict(payload["optimizer_state_dict"])
    assert_same(student.state_dict(), payload["student_state_dict"])
    assert_same(opt.state_dict(), payload["optimizer_state_dict"])
    g = torch.Generator()
    g.set_state(payload["generator"])
    assert torch.equal(g.get_state(), payload["generator"])


@pytest.mark.sim
def test_real_student_exports(smoke_run, tmp_path, capsys):
    from march.export.bundle import main

    out = tmp_path / "student.onnx"
    main([f"student_ckpt={smoke_run / 'student' / 'latest.pt'}", f"out={out}"])
    text = capsys.readouterr().out
    assert out.is_file() and out.stat().st_size > 10_000
    assert float(re.search(r"max \|onnx - torch\| = (\S+)", text).group(1)) < 1e-4


def test_ordered_dict_and_size_are_plain():
    assert non_plain({"a": OrderedDict(w=torch.ones(1)), "s": torch.Size([1, 2])}) is None
    assert "set at payload['a']" in non_plain({"a": {1, 2}})
