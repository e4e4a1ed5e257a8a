"""A run resumes anywhere with its whole state (issue 21): random streams across devices, the
resumed config.yaml as data, torn rows and durable writes; the curriculum and a CUDA run's
directory resumed on the CPU (sim tests).
"""

from __future__ import annotations

import csv
import os
import random
import stat
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from saved_runs import resume as _resume
from saved_runs import saved_run as _saved_run
from saved_runs import train_cli

from march.config import ConfigError
from march.config.cli import load
from march.learn.metrics import METRIC_COLUMNS, append_row, drop_torn_row, truncate_rows
from march.learn.train_state import (
    CUDA_STATE_BYTES,
    collect_streams,
    restore_streams,
    stream_seed,
)
from march.store.checkpoint import (
    CheckpointError,
    load_checkpoint,
    save_atomic,
    save_checkpoint,
    write_json_atomic,
)

ROOT = Path(__file__).resolve().parent.parent


def cuda_generator_state(seed: int, offset: int) -> torch.Tensor:
    """A CUDA generator's ``get_state()`` as a CUDA run writes it: seed and Philox offset."""
    return torch.tensor([seed, offset], dtype=torch.int64).view(torch.uint8).clone()


def draws(gens: dict[str, torch.Generator]) -> dict[str, list]:
    out = {
        "torch": torch.rand(5).tolist(),
        "numpy": np.random.rand(5).tolist() + [float(np.random.standard_normal())],
        "python": [random.random() for _ in range(5)] + [random.gauss(0, 1)],
    }
    out.update({k: torch.rand(5, generator=g).tolist() for k, g in gens.items()})
    return out


# ------------------------------------------------------------------ random streams (pure)


@pytest.mark.parametrize("seed", range(5))
def test_every_stream_continues_where_it_stopped(seed):
    torch.manual_seed(seed)
    np.random.seed(seed + 1)
    random.seed(seed + 2)
    np.random.standard_normal()  # a cached gaussian in numpy's state
    random.gauss(0, 1)  # and in Python's
    gens = {"planner": torch.Generator().manual_seed(seed + 3)}
    gens["distill"] = torch.Generator().manual_seed(seed + 4)
    for g in gens.values():
        torch.rand(seed + 1, generator=g)
    saved = collect_streams("cpu", gens)
    want = draws(gens)
    # Another process: everything drawn differently since.
    torch.manual_seed(99)
    np.random.seed(99)
    random.seed(99)
    fresh = {k: torch.Generator().manual_seed(99) for k in gens}
    assert restore_streams(saved, "cpu", seed, 3, "here", fresh) is None
    assert draws(fresh) == want


def test_a_cuda_generator_state_on_the_cpu_is_reseeded_in_one_line():
    gens = {"planner": torch.Generator(), "distill": torch.Generator()}
    saved = collect_streams("cpu", gens)
    saved.update(
        device="cuda:0",
        cuda=cuda_generator_state(7, 1024),
        planner=cuda_generator_state(0, 4096),
        distill=cuda_generator_state(0, 512),
    )
    torch_state = saved["torch"].clone()
    line = restore_streams(saved, "cpu", 5, 12, "resume=x", gens)
    assert line is not None and "\n" not in line
    assert line.startswith("saved on cuda:0, resumed on cpu: the stream(s) planner, distill")
    assert "reseeded from seed 5 and iteration 12" in line and "CUDA generator" in line
    for name, g in gens.items():
        want = torch.Generator().manual_seed(stream_seed(5, 12, name))
        assert torch.equal(torch.rand(4, generator=g), torch.rand(4, generator=want)), name
    assert torch.equal(torch.get_rng_state(), torch_state)  # the CPU stream continues
    # Deterministic: the same seed and iteration give the same streams; others differ.
    seeds = {stream_seed(s, it, n) for s in (0, 1) for it in (0, 12) for n in ("planner", "x")}
    assert len(seeds) == 8 and stream_seed(5, 12, "planner") == stream_seed(5, 12, "planner")
    assert CUDA_STATE_BYTES == 16 and torch.Generator().get_state().numel() != 16


@pytest.mark.parametrize(
    "bad,named",
    [
        ({"torch": torch.zeros(3)}, "streams.torch"),
        ({"planner": torch.zeros(4, dtype=torch.int64)}, "streams.planner"),
        ({"numpy": {"kind": "MT19937"}}, "streams.numpy"),
        ({"python": {"version": 3}}, "streams.python"),
    ],
)
def test_a_broken_stream_is_refused_in_one_line(bad, named):
    gens = {"planner": torch.Generator()}
    saved = {**collect_streams("cpu", gens), **bad}
    with pytest.raises(CheckpointError) as err:
        restore_streams(saved, "cpu", 0, 1, "resume=r: latest.pt", gens)
    assert named in str(err.value) and "\n" not in str(err.value)
    assert str(err.value).startswith("resume=r: latest.pt")


def test_streams_survive_a_checkpoint_and_stay_on_the_cpu(tmp_path):
    gens = {"planner": torch.Generator().manual_seed(3)}
    payload = {
        "kind": "teacher",
        "iteration": 2,
        "streams": collect_streams("cpu", gens),
        "curriculum": {"terrain_levels": torch.tensor([0, 3, 1])},
    }
    save_checkpoint(payload, tmp_path, 2)
    back = load_checkpoint(tmp_path / "latest.pt", "teacher", device="meta")
    assert back["streams"]["torch"].device.type == "cpu"
    assert back["curriculum"]["terrain_levels"].tolist() == [0, 3, 1]
    assert back["streams"]["python"]["internal"].dtype == torch.int64


# ------------------------------------------------------------------ the resumed config is data


@pytest.mark.parametrize(
    "value",
    [
        '"\\x24{oc.env:MY_SECRET}"',  # YAML's double-quote escape of '$'
        '"\\u0024{oc.env:MY_SECRET}"',
        "\"${oc.decode:'${oc.env:MY_SECRET}'}\"",
        '"\\x24{oc.decode:\\x27\\x24{oc.env:MY_SECRET}\\x27}"',
        "'\\${oc.env:MY_SECRET}'",  # OmegaConf's escaped form: a literal ${ that a save re-arms
        "prefix-${oc.env:MY_SECRET}-suffix",
    ],
)
def test_a_resumed_config_with_an_interpolation_is_refused_naming_the_key(tmp_path, value):
    run = _saved_run(tmp_path)
    text = (run / "config.yaml").read_text()
    assert "\nout: null\n" in text
    (run / "config.yaml").write_text(text.replace("\nout: null\n", f"\nout: {value}\n"))
    os.environ["MY_SECRET"] = "s3cret"
    try:
        with pytest.raises(ConfigError) as err:
            _resume(run)
    finally:
        del os.environ["MY_SECRET"]
    msg = str(err.value)
    assert "key out holds a '${...}' interpolation or resolver" in msg, msg
    assert "\n" not in msg and "s3cret" not in msg
    assert "s3cret" not in (run / "config.yaml").read_text()


def test_an_interpolation_in_a_list_or_a_key_is_refused(tmp_path):
    run = _saved_run(tmp_path)
    text = (run / "config.yaml").read_text()
    (run / "config.yaml").write_text(text + 'extra:\n  - fine\n  - "\\x24{oc.env:HOME}"\n')
    with pytest.raises(ConfigError, match=r"key extra\[1\] holds"):
        _resume(run)
    (run / "config.yaml").write_text(text + '"\\x24{oc.env:HOME}": 1\n')
    with pytest.raises(ConfigError, match="holds a"):
        _resume(run)


def test_a_plain_dollar_is_data(tmp_path):
    run = _saved_run(tmp_path)
    text = (run / "config.yaml").read_text()
    (run / "config.yaml").write_text(text.replace("\nout: null\n", '\nout: "cost_$5_{x}.png"\n'))
    cfg, _ = _resume(run)
    assert cfg.out == "cost_$5_{x}.png"


# ------------------------------------------------------------------ resume on another device


def test_resume_may_change_the_device_and_nothing_else_of_compute(tmp_path, monkeypatch):
    import march.config.cli as cli

    monkeypatch.setattr(cli, "cuda_available", lambda: False)
    run = _saved_run(tmp_path, "compute.device=cuda:0")
    cfg, notes = _resume(run, "compute.device=cpu", "compute.torch_threads=1")
    assert cfg.compute.device == "cpu" and cfg.compute.torch_threads == 1
    assert cfg.compute.num_envs == 4 and cfg.compute.name == "smoke"
    assert "[resume] compute.device: cuda:0 -> cpu" in notes
    for other in ("compute.num_envs=8", "compute=cpu", "compute.eval_num_envs=2"):
        with pytest.raises(ConfigError, match="cannot change on resume"):
            _resume(run, "compute.device=cpu", other)


def test_a_cuda_run_resumed_without_cuda_names_the_device_and_the_override(tmp_path, monkeypatch):
    import march.config.cli as cli

    monkeypatch.setattr(cli, "cuda_available", lambda: False)
    run = _saved_run(tmp_path, "compute.device=cuda:0")
    with pytest.raises(ConfigError) as err:
        _resume(run)
    msg = str(err.value)
    assert "the run was saved on cuda:0 and CUDA is not available" in msg
    assert f"resume={run} compute.device=cpu" in msg and "\n" not in msg


# ------------------------------------------------------------------ torn rows, durable writes


def _write_csv(path: Path, rows: list[dict], tail: str = "") -> None:
    for r in rows:
        append_row(path, METRIC_COLUMNS, r)
    with path.open("a", newline="") as f:
        f.write(tail)


@pytest.mark.parametrize(
    "tail",
    ["teacher,", "teacher,3,9", "student", "teacher,3,96,0.5,1.0,2.0,3.0,0.25,1,2,3,4,5,6"],
)
def test_a_torn_last_row_is_dropped_with_one_line(tmp_path, capsys, tail):
    path = tmp_path / "metrics.csv"
    rows = [{"stage": "teacher", "iteration": k, "env_steps": 32 * k} for k in (1, 2)]
    _write_csv(path, rows, tail)
    truncate_rows(path, "teacher", 2)
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1 and out[0].startswith("[resume] metrics.csv: dropped a torn last row")
    with path.open(newline="") as f:
        got = [(r["stage"], int(r["iteration"])) for r in csv.DictReader(f)]
    assert got == [("teacher", 1), ("teacher", 2)]
    assert path.read_bytes().endswith(b"\r\n")
    append_row(path, METRIC_COLUMNS, {"stage": "teacher", "iteration": 3})  # appends cleanly
    with path.open(newline="") as f:
        assert [int(r["iteration"]) for r in csv.DictReader(f)] == [1, 2, 3]


def test_a_whole_file_is_left_alone(tmp_path, capsys):
    path = tmp_path / "eval.csv"
    _write_csv(path, [{"stage": "teacher", "iteration": 1}])
    before = path.read_bytes()
    assert not drop_torn_row(path)
    truncate_rows(path, "teacher", 1)
    assert path.read_bytes() == before and capsys.readouterr().out == ""


def test_appends_and_atomic_replaces_are_fsynced_with_their_directory(tmp_path, monkeypatch):
    synced: list[str] = []
    real = os.fsync

    def spy(fd):
        synced.append("dir" if stat.S_ISDIR(os.fstat(fd).st_mode) else "file")
        return real(fd)

    monkeypatch.setattr(os, "fsync", spy)
    append_row(tmp_path / "m.csv", METRIC_COLUMNS, {"stage": "teacher", "iteration": 1})
    assert synced == ["file"]
    synced.clear()
    save_atomic({"kind": "teacher"}, tmp_path / "x.pt")
    assert synced == ["file", "dir"]
    synced.clear()
    write_json_atomic({"state": "done"}, tmp_path / "status.json")
    assert synced == ["file", "dir"]
    synced.clear()
    _write_csv(tmp_path / "m.csv", [{"stage": "teacher", "iteration": 2}], "teacher,")
    synced.clear()
    truncate_rows(tmp_path / "m.csv", "teacher", 0)  # torn row dropped, then rows truncated
    assert synced == ["file", "dir", "file", "dir"]


def test_a_bad_file_under_resume_is_named_by_resume(tmp_path):
    (tmp_path / "latest.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError) as err:
        load_checkpoint(tmp_path / "latest.pt", "teacher", source=f"resume={tmp_path}: x")
    assert str(err.value).startswith(f"resume={tmp_path}: x: not a readable checkpoint")
    assert "teacher_ckpt=" not in str(err.value)


def test_decisions_say_one_order_of_the_checkpoint_files():
    text = (ROOT / "docs" / "decisions.md").read_text()
    assert "writes\n  `model_<it>.pt` before `latest.pt`" not in text
    assert "latest.pt is written before model_<it>.pt" in text


# ------------------------------------------------------------------ sim: a CUDA run dir on CPU


def craft_cuda_run(run: Path) -> Path:
    """A CPU teacher run rewritten as a ``cuda:0`` run leaves its directory: config.yaml on
    cuda:0, checkpoints whose generator states are CUDA ones (16 bytes) and a CUDA stream."""
    cfg = OmegaConf.load(run / "config.yaml")
    cfg.compute.device = "cuda:0"
    OmegaConf.save(cfg, run / "config.yaml")
    for path in sorted((run / "teacher").glob("*.pt")):
        payload = load_checkpoint(path, "teacher")
        payload["config"]["compute"]["device"] = "cuda:0"
        s = payload["streams"]
        s.update(device="cuda:0", cuda=cuda_generator_state(0, 2**20))
        s["planner"] = cuda_generator_state(0, 4 * 2**10)
        save_atomic(payload, path)
    return run


@pytest.mark.sim
def test_a_cuda_run_directory_resumes_on_the_cpu_with_the_override(tmp_path):
    run = tmp_path / "run"
    first = train_cli(
        "compute=smoke",
        "stage=teacher",
        "teacher.max_iterations=1",
        "eval.episode_length_s=0.1",  # the resume is tested, not the walking: 5-step rollouts
        f"hydra.run.dir={run}",
        timeout=900,
    )
    assert first.returncode == 0, first.stdout[-2000:] + first.stderr[-2000:]
    craft_cuda_run(run)
    refused = train_cli(f"resume={run}", timeout=900)
    err = refused.stderr.strip().splitlines()
    assert refused.returncode == 2 and len(err) == 1, refused.stderr
    assert "saved on cuda:0" in err[0] and "compute.device=cpu" in err[0]
    assert "[env]" not in refused.stdout and "Traceback" not in refused.stderr
    resumed = train_cli(
        f"resume={run}", "compute.device=cpu", "teacher.max_iterations=2", timeout=900
    )
    out = resumed.stdout
    assert resumed.returncode == 0, out[-3000:] + resumed.stderr[-3000:]
    assert "[resume] compute.device: cuda:0 -> cpu" in out
    assert "at iteration 1" in out
    assert "saved on cuda:0, resumed on cpu: the stream(s) planner cannot continue" in out
    assert "reseeded from seed 0 and iteration 1" in out
    payload = load_checkpoint(run / "teacher" / "latest.pt", "teacher")
    assert payload["iteration"] == 2 and payload["streams"]["device"] == "cpu"
    assert payload["streams"]["planner"].numel() != 16  # a CPU generator's state again
    assert OmegaConf.load(run / "config.yaml").compute.device == "cpu"
    with (run / "metrics.csv").open() as f:
        rows = [r for r in csv.DictReader(f) if r["stage"] == "teacher"]
    assert [int(r["iteration"]) for r in rows] == [1, 2]
    assert all(r["mean_terrain_level"] != "" for r in rows)


# ------------------------------------------------------------------ sim: the curriculum


CURRICULUM = (
    "compute=smoke",
    "curriculum.promote_fraction=0.01",  # ~1.5 cm along the course promotes
    "curriculum.demote_fraction=0.0",
    "curriculum.max_init_level=2",  # envs start on different levels
    "env.episode_length_s=0.3",  # a time-out every 15 steps: the curriculum runs often
)


@pytest.mark.sim
def test_a_killed_teacher_resumes_its_levels_env_by_env_and_its_streams(tmp_path):
    from march.env.build import make_env
    from march.env.env_state import planner_generator
    from march.learn.metrics import MetricsLog
    from march.learn.teacher import TeacherRunner

    cfg = load(list(CURRICULUM))
    run = tmp_path / "run"
    run.mkdir()
    env = make_env(cfg, "teacher")
    initial = env.scene.terrain.terrain_levels.clone()
    log = MetricsLog(run, cfg.logger, "t")
    runner = TeacherRunner(env, cfg, run, log)
    moved_at = None
    for k in range(1, 7):
        runner.learn(k)  # saves at k (the stage's last iteration)
        if not torch.equal(env.scene.terrain.terrain_levels, initial):
            moved_at = k
            break
    assert moved_at is not None, "the curriculum moved no env in 6 iterations"
    saved = load_checkpoint(run / "teacher" / "latest.pt", "teacher")
    assert saved["iteration"] == moved_at
    levels = saved["curriculum"]["terrain_levels"]
    assert torch.equal(levels, env.scene.terrain.terrain_levels.cpu())
    assert not torch.equal(levels, initial.cpu())
    clocks = saved["episode"]["episode_length_buf"]
    assert torch.equal(clocks, env.episode_length_buf.cpu())
    # What every stream would have drawn next, had the run not been killed here.
    want = draws({"planner": planner_generator(env)})
    log.close()
    env.close()
    del runner, env

    env = make_env(cfg, "teacher")
    log = MetricsLog(run, cfg.logger, "t")
    runner = TeacherRunner(env, cfg, run, log)
    assert torch.equal(env.scene.terrain.terrain_levels.cpu(), initial.cpu())  # built afresh
    assert runner.try_resume()
    got_levels = env.scene.terrain.terrain_levels.cpu()
    for e in range(env.num_envs):
        assert int(got_levels[e]) == int(levels[e]), f"env {e}"
    origins = env.scene.terrain.terrain_origins[
        env.scene.terrain.terrain_levels, env.scene.terrain.terrain_types
    ]
    assert torch.equal(env.scene.env_origins, origins)
    assert torch.equal(env.episode_length_buf.cpu(), clocks)
    assert draws({"planner": planner_generator(env)}) == want
    # The next iteration runs from there; its row holds the mean level.
    runner.learn(moved_at + 1)
    with (run / "metrics.csv").open() as f:
        rows = [r for r in csv.DictReader(f) if r["stage"] == "teacher"]
    assert [int(r["iteration"]) for r in rows] == list(range(1, moved_at + 2))
    assert float(rows[moved_at - 1]["mean_terrain_level"]) == pytest.approx(
        float(levels.float().mean()), abs=1e-6
    )
    log.close()
    env.close()
