"""Per-term training logs (issue 36, item 1): each reward term's contribution, each termination's
share of ended episodes and the curriculum level's spread, summed on the device and read once;
checked against the same quantities read step by step from mjlab's managers, and the metrics
file and tensorboard names they go to."""

from __future__ import annotations

import csv

import pytest
import torch

from march.config.cli import load
from march.learn.metrics import MetricsLog, _scalar_name

STEPS = 12


@pytest.mark.sim
def test_meter_equals_the_managers_step_by_step():
    from march.env.build import make_env

    cfg = load(["compute=smoke", "reward=modelfree", "dr=none", "env.episode_length_s=0.1"])
    env = make_env(cfg, "teacher", num_envs=4)
    try:
        env.reset()
        meter = env.term_meter
        rm, tm = env.reward_manager, env.termination_manager
        want_r = torch.zeros(len(rm.active_terms))
        want_t = torch.zeros(len(tm.active_terms))
        episodes = 0
        total = 0.0
        gen = torch.Generator().manual_seed(0)
        for _ in range(STEPS):
            act = 0.3 * torch.randn(4, env.action_manager.total_action_dim, generator=gen)
            _, reward, terminated, truncated, _ = env.step(act)
            want_r += rm._step_reward.sum(0).cpu() * env.step_dt
            want_t += torch.stack([tm._term_dones[k] for k in tm.active_terms]).sum(1).cpu()
            episodes += int((terminated | truncated).sum())
            total += float(reward.sum())
        row = meter.pop()
        n = STEPS * 4
        for i, k in enumerate(rm.active_terms):
            assert row[f"reward/{k}"] == pytest.approx(float(want_r[i]) / n, rel=1e-5, abs=1e-9)
        # the terms add up to the mean step reward
        parts = sum(row[f"reward/{k}"] for k in rm.active_terms)
        assert parts == pytest.approx(total / n, rel=1e-5, abs=1e-9)
        assert episodes >= 4  # 0.1 s episodes: every env timed out at least once
        for i, k in enumerate(tm.active_terms):
            assert row[f"termination/{k}"] == pytest.approx(float(want_t[i]) / episodes)
        assert row["termination/time_out"] > 0
        levels = env.scene.terrain.terrain_levels.float()
        assert row["terrain_level_std"] == pytest.approx(float(levels.std(correction=0)))
        # read once and started over
        again = meter.pop()
        assert all(again[f"reward/{k}"] == 0.0 for k in rm.active_terms)
    finally:
        env.close()


def test_metrics_file_keeps_every_term_column_and_external_names(tmp_path):
    from march.config import LoggerCfg

    log = MetricsLog(tmp_path, LoggerCfg(), "x")
    base = {"iteration": 1, "env_steps": 10, "wall_s": 1.0}
    log.log({"stage": "teacher", **base, "reward/clf": 0.5, "termination/tilt": 0.25})
    log.log({"stage": "student", **base, "loss/nll": 2.0})
    again = MetricsLog(tmp_path, LoggerCfg(), "x")  # a resumed run: the file's columns stay
    again.log({"stage": "student", **base, "iteration": 2, "loss/nll": 1.0})
    with (tmp_path / "metrics.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [r["reward/clf"] for r in rows] == ["0.5", "", ""]
    assert [r["termination/tilt"] for r in rows] == ["0.25", "", ""]
    assert [r["loss/nll"] for r in rows] == ["", "2", "1"]
    assert _scalar_name("teacher", "reward/clf") == "Teacher/Episode_Reward/clf"
    assert _scalar_name("teacher", "termination/tilt") == "Teacher/Episode_Termination/tilt"
    assert _scalar_name("student", "reward/clf") == "Distill/Episode_Reward/clf"
    assert _scalar_name("student", "loss/nll") == "Distill/loss/nll"


def _wandb_points(run_dir) -> dict[str, dict[int, float]]:
    """Every history point of the offline wandb run under ``run_dir``, read from its
    ``run-*.wandb`` file (a LevelDB-style log of protobuf records: 7-byte file header, 32 KiB
    blocks, each record chunk behind a 7-byte header of checksum, length and type). wandb-core
    writes the file behind ``finish()``: read it once its ``exit`` record is there (<= 60 s)."""
    import time

    deadline = time.monotonic() + 60
    while True:
        points, done = _read_wandb(run_dir)
        if done or time.monotonic() > deadline:
            assert done, "the offline wandb run has no exit record after 60 s"
            return points
        time.sleep(0.5)


def _read_wandb(run_dir) -> tuple[dict[str, dict[int, float]], bool]:
    import struct

    from wandb.proto import wandb_internal_pb2 as pb

    (path,) = run_dir.glob("wandb/offline-run-*/run-*.wandb")
    data = path.read_bytes()
    done = False
    assert data[:4] == b":W&B"
    points: dict[str, dict[int, float]] = {}
    i, buf = 7, b""
    while i + 7 <= len(data):
        if 32768 - i % 32768 < 7:  # block trailer: padding
            i += 32768 - i % 32768
            continue
        _, length, kind = struct.unpack("<IHB", data[i : i + 7])
        if kind == 0 and length == 0:
            break
        buf += data[i + 7 : i + 7 + length]
        i += 7 + length
        if kind in (1, 4):  # FULL or LAST chunk: a whole record
            rec = pb.Record()
            rec.ParseFromString(buf)
            buf = b""
            done |= rec.WhichOneof("record_type") == "exit"
            if rec.WhichOneof("record_type") == "history":
                step = rec.history.step.num
                for item in rec.history.item:
                    key = item.key or "/".join(item.nested_key)
                    if not key.startswith("_"):
                        points.setdefault(key, {})[step] = float(item.value_json)
    return points, done


def _tensorboard_points(run_dir) -> dict[str, dict[int, float]]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(run_dir / "tensorboard"), size_guidance={"scalars": 0})
    acc.Reload()
    return {tag: {e.step: e.value for e in acc.Scalars(tag)} for tag in acc.Tags()["scalars"]}


@pytest.mark.parametrize("logger", ["tensorboard", "wandb"])
def test_both_stages_reach_the_logger_under_their_own_prefix_on_one_rising_step(
    tmp_path, logger, monkeypatch
):
    """Teacher rows at env steps 32 and 64, then distillation rows at its own 32 and 64 (and a
    resumed distillation process logging its third row): every point is read back from the
    logger's files, the teacher's under Teacher/, the student's under Distill/ at 64 + its env
    steps; no point is lost or lands on the other stage's curve (issue 49: wandb dropped every
    student row, tensorboard mixed both stages in Episode_Reward/clf). A column no list names
    (``clf/V``) reaches metrics.csv and the logger too."""
    from march.config import LoggerCfg

    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_SILENT", "true")
    cfg = LoggerCfg(name=logger, project="march-test")
    rows = [
        {"stage": "teacher", "iteration": 1, "env_steps": 32, "reward/clf": 0.5, "clf/V": 2.0},
        {"stage": "teacher", "iteration": 2, "env_steps": 64, "reward/clf": 0.75, "clf/V": 1.0},
        {"stage": "student", "iteration": 1, "env_steps": 32, "reward/clf": 0.25, "loss/nll": 3.0},
        {"stage": "student", "iteration": 2, "env_steps": 64, "reward/clf": 0.375, "loss/nll": 2.0},
    ]
    log = MetricsLog(tmp_path, cfg, "x")
    for row in rows:
        log.log({**row, "wall_s": 1.0})
    log.close()
    if logger == "tensorboard":  # a resumed distillation: a new process, a new writer
        log = MetricsLog(tmp_path, cfg, "x")
        log.log({"stage": "student", "iteration": 3, "env_steps": 96, "loss/nll": 1.5})
        log.close()
    points = _tensorboard_points(tmp_path) if logger == "tensorboard" else _wandb_points(tmp_path)
    assert points["Teacher/Episode_Reward/clf"] == {32: 0.5, 64: 0.75}
    assert points["Distill/Episode_Reward/clf"] == {96: 0.25, 128: 0.375}
    assert points["Teacher/clf/V"] == {32: 2.0, 64: 1.0}
    nll = {96: 3.0, 128: 2.0} | ({160: 1.5} if logger == "tensorboard" else {})
    assert points["Distill/loss/nll"] == nll
    assert points["Distill/env_steps"] == {s + 64: float(s) for s in (32, 64, 96)[: len(nll)]}
    assert not any(k.startswith(("Episode_", "teacher/", "student/")) for k in points)
    with (tmp_path / "metrics.csv").open() as f:
        assert [r["clf/V"] for r in csv.DictReader(f)][:2] == ["2", "1"]
    print(f"{logger}: {sum(len(v) for v in points.values())} points read back")
