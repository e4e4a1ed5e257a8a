"""Tests for analysis/figures.py on synthetic run directories with known numbers."""

from __future__ import annotations

import ast
import contextlib
import importlib.util
import io
import json
import math
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "analysis" / "figures.py"


def _load_module():
    spec = importlib.util.spec_from_file_location("march_analysis_figures", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look the module up by name
    spec.loader.exec_module(mod)
    return mod


fig = _load_module()

STEPS_PER_IT = 98304
SEED_OFF = {0: -1.0, 1: 1.0, 2: 0.0}  # symmetric per-seed offsets: seed means average out
STUDENT_BASE = {"full": 1.0, "no_transformer": 0.8, "no_mdn": 0.6}
TEACHER_SLOPE = {"clf": 0.1, "modelfree": 0.05}  # teacher distance = slope * iteration
EVAL_D0 = {"clf": 3.0, "modelfree": 2.0}
# final summary.json per (reward, variant, seed): distance, success, torque, jerk, reward
FINAL = {
    ("clf", "full", 0): (3.8, 0.7, 9.5, 45.0, 1.4),
    ("clf", "full", 1): (4.2, 0.9, 10.5, 55.0, 1.6),
    ("clf", "full", 2): (4.0, 0.8, 10.0, 50.0, 1.5),
    ("modelfree", "full", 0): (2.8, 0.3, 8.6, 55.0, 1.1),
    ("modelfree", "full", 1): (3.2, 0.5, 9.0, 65.0, 1.3),
    ("clf", "no_transformer", 0): (3.6, 0.6, 11.0, 40.0, 1.2),
    ("clf", "no_mdn", 0): (3.0, 0.4, 12.5, 70.0, 0.9),
}
KEYS = ["distance_m", "success_rate", "abs_torque_nm", "abs_ang_jerk", "reward"]
RUN_SE = 0.3


def _config_yaml(reward, variant, seed, stage="all"):
    curriculum = "flat_first" if reward == "modelfree" else "stones"
    return (
        f"reward:\n  name: {reward}\nstudent:\n  variant: {variant}\n"
        f"curriculum:\n  name: {curriculum}\nseed: {seed}\nstage: {stage}\n"
        "compute:\n  name: smoke\n"
    )


def _teacher_rows(reward, seed, n_iter):
    off = SEED_OFF[seed]
    return [
        {
            "stage": "teacher",
            "iteration": it,
            "env_steps": it * STEPS_PER_IT,
            "wall_s": 0.5 * it,
            "mean_reward": 0.5 * it + off,
            "mean_episode_length": 100 + it,
            "mean_distance_m": TEACHER_SLOPE[reward] * it,
            "value_loss": 0.1,
            "surrogate_loss": -0.01,
            "entropy": 1.0,
            "learning_rate": 5e-5,
        }
        for it in range(n_iter)
    ]


def _student_rows(reward, variant, seed, n_iter=50):
    base = STUDENT_BASE[variant] - (0.5 if reward == "modelfree" else 0.0)
    return [
        {
            "stage": "student",
            "iteration": it,
            "env_steps": it * 1000,
            "wall_s": 0.1 * it,
            "mean_reward": 0.2,
            "mean_episode_length": 300,
            "mean_distance_m": 2.0,
            "loss": 1.0 / (it + 1),
            "action_error": 0.1,
            "teacher_reward": base + 0.01 * it + 0.1 * SEED_OFF[seed],
        }
        for it in range(n_iter)
    ]


def _eval_rows(reward, seed):
    rows = []
    for it in (0, 25, 49):
        row = {"stage": "student", "iteration": it, "env_steps": it * 1000, "n_rollouts": 64}
        vals = {
            "distance_m": EVAL_D0[reward] + 0.02 * it + 0.2 * SEED_OFF[seed],
            "success_rate": 0.5,
            "abs_torque_nm": 10.0,
            "abs_ang_jerk": 50.0,
            "reward": 1.0,
        }
        for k, v in vals.items():
            row[f"mean_{k}"] = v
            row[f"se_{k}"] = 0.05
        rows.append(row)
    # a teacher evaluation row that must not enter the (student) baseline figure
    rows.append({**rows[-1], "stage": "teacher", "iteration": 59, "mean_distance_m": 99.0})
    return rows


def _make_run(
    d: Path,
    reward,
    variant,
    seed,
    *,
    hydra_only=False,
    state="done",
    teacher_iters=60,
    student=True,
    final=True,
    truncate=False,
    status=True,
):
    d.mkdir(parents=True)
    cfg = _config_yaml(reward, variant, seed)
    if hydra_only:
        (d / ".hydra").mkdir()
        (d / ".hydra" / "config.yaml").write_text(cfg)
    else:
        (d / "config.yaml").write_text(cfg)
    rows = _teacher_rows(reward, seed, teacher_iters)
    if student:
        rows += _student_rows(reward, variant, seed)
    text = pd.DataFrame(rows).to_csv(index=False)
    if truncate:
        text += "teacher,30,2949120,15.0,1"  # cut off mid-row, no newline
    (d / "metrics.csv").write_text(text)
    if student:
        pd.DataFrame(_eval_rows(reward, seed)).to_csv(d / "eval.csv", index=False)
    if final:
        summary = {"stage": "student", "iteration": 49, "env_steps": 49000, "n_rollouts": 64}
        for k, v in zip(KEYS, FINAL[(reward, variant, seed)], strict=True):
            summary[f"mean_{k}"] = v
            summary[f"se_{k}"] = RUN_SE
        (d / "summary.json").write_text(json.dumps(summary))
    if status:
        error = "RuntimeError: simulated crash in PPO update" if state == "failed" else None
        (d / "status.json").write_text(json.dumps({"state": state, "error": error}))


def build_tree(root: Path) -> tuple[Path, Path]:
    base = root / "sweep_base"
    base.mkdir(parents=True)
    (base / "multirun.yaml").write_text("hydra:\n  mode: MULTIRUN\n")
    _make_run(base / "0", "clf", "full", 0)
    _make_run(base / "1", "clf", "full", 1, hydra_only=True)
    _make_run(base / "2", "modelfree", "full", 0)
    _make_run(base / "3", "modelfree", "full", 1)
    abl = root / "sweep_abl"
    abl.mkdir()
    (abl / "multirun.yaml").write_text("hydra:\n  mode: MULTIRUN\n")
    _make_run(abl / "0", "clf", "full", 2)
    _make_run(abl / "1", "clf", "no_transformer", 0)
    _make_run(abl / "2", "clf", "no_mdn", 0)
    # crashed: failed during the teacher stage, metrics.csv cut off mid-row
    _make_run(
        abl / "3",
        "clf",
        "no_mdn",
        1,
        state="failed",
        teacher_iters=30,
        student=False,
        final=False,
        truncate=True,
    )
    # never reported a status (killed before status.json was written)
    _make_run(
        abl / "4",
        "clf",
        "no_transformer",
        1,
        teacher_iters=10,
        student=False,
        final=False,
        status=False,
    )
    return base, abl


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    root = tmp_path_factory.mktemp("runs")
    base, abl = build_tree(root)
    out = root / "out"
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = fig.main(
            [str(base), str(abl), "--out", str(out), "--smooth", "4", "--target-distance", "2.0"]
        )
    return {
        "root": root,
        "base": base,
        "abl": abl,
        "out": out,
        "code": code,
        "stdout": buf.getvalue(),
    }


def test_discovery_and_listing_names_crashed_run(tree):
    assert tree["code"] == 0
    listing = pd.read_csv(tree["out"] / "runs.csv")
    assert len(listing) == 9
    assert (listing["status"] == "complete").sum() == 7
    crashed = listing[listing["run"] == "sweep_abl/3"].iloc[0]
    assert crashed["status"] == "failed"
    assert "simulated crash" in crashed["error"]
    assert "cut off" in crashed["issues"]
    assert crashed["teacher_rows"] == 30  # the partial 31st row is dropped
    nostatus = listing[listing["run"] == "sweep_abl/4"].iloc[0]
    assert nostatus["status"] == "incomplete (no status.json)"
    hydra_only = listing[listing["run"] == "sweep_base/1"].iloc[0]
    assert (hydra_only["reward"], hydra_only["seed"]) == ("clf", 1)
    md = (tree["out"] / "runs.md").read_text()
    assert md.count("sweep_abl/3") == 1 and "failed" in md
    out = tree["stdout"]
    assert "sweep_abl/3: failed" in out and "simulated crash" in out
    assert "runs found: 9 (7 complete, 1 failed, 1 other incomplete)" in out


def test_final_table_numbers_and_relative_differences(tree):
    table = pd.read_csv(tree["out"] / "final_metrics.csv")
    assert len(table) == 4  # clf/full, clf/no_transformer, clf/no_mdn, modelfree/full
    by = {(r.reward, r.variant): r for r in table.itertuples()}
    ref = by[("clf", "full")]
    mf = by[("modelfree", "full")]
    assert ref.n_runs == 3 and mf.n_runs == 2
    assert ref.mean_abs_torque_nm == pytest.approx(10.0, abs=1e-12)
    assert mf.mean_abs_torque_nm == pytest.approx(8.8, abs=1e-12)
    # SE across seeds: std(ddof=1)/sqrt(n)
    assert ref.se_abs_torque_nm == pytest.approx(0.5 / math.sqrt(3), abs=1e-12)
    assert mf.se_abs_torque_nm == pytest.approx(0.2, abs=1e-12)
    assert mf.rel_abs_torque_nm == pytest.approx(-0.12, abs=1e-12)
    assert mf.vs_clf_full == "distance -25%, success -50%, torque -12%, jerk +20%, reward -20%"
    assert ref.vs_clf_full == "reference"
    # a single-run group keeps its own rollout SE
    nt = by[("clf", "no_transformer")]
    assert nt.n_runs == 1 and nt.se_abs_torque_nm == pytest.approx(RUN_SE)
    assert "torque +10%" in nt.vs_clf_full
    assert "torque +25%" in by[("clf", "no_mdn")].vs_clf_full
    md = (tree["out"] / "final_metrics.md").read_text()
    mf_line = next(ln for ln in md.splitlines() if ln.startswith("| modelfree | full |"))
    assert "8.8 ± 0.2" in mf_line and "torque -12%" in mf_line
    assert "| clf | full | 3 | 4 ± 0.1155 |" in md
    assert "modelfree/full (n=2)" in tree["stdout"] and "torque -12%" in tree["stdout"]


def test_every_figure_written(tree):
    for stem in ("ablation", "baseline", "teacher_curves"):
        png = (tree["out"] / f"{stem}.png").read_bytes()
        assert png[:8] == b"\x89PNG\r\n\x1a\n"
        width, height = struct.unpack(">II", png[16:24])
        assert width > 600 and height > 300
        pdf = (tree["out"] / f"{stem}.pdf").read_bytes()
        assert pdf[:5] == b"%PDF-" and len(pdf) > 1000
    written = [ln for ln in tree["stdout"].splitlines() if ln.startswith("wrote ")]
    assert len(written) == 1 and written[0].startswith("wrote 11 files")


def test_sample_efficiency_iteration(tree):
    eff = pd.read_csv(tree["out"] / "sample_efficiency.csv")
    by = {r.reward: r for r in eff.itertuples()}
    # smoothed (window 4) distance at it = slope * (it - 1.5) -> first >= 2.0
    assert by["clf"].iteration == 22
    assert by["modelfree"].iteration == 42
    assert by["clf"].env_steps == 22 * STEPS_PER_IT
    assert "sweep_base/2:42" in by["modelfree"].per_run
    assert "sweep_abl/3:22" in by["clf"].per_run  # the crashed run still contributes
    assert "clf: iteration 22" in tree["stdout"]
    assert "modelfree: iteration 42" in tree["stdout"]


def test_ablation_and_baseline_data(tree):
    runs = fig.discover([tree["base"], tree["abl"]])
    notes: list[str] = []
    abl = fig.ablation_data(runs, 4, notes)
    assert list(abl) == ["full", "no_transformer", "no_mdn"]
    last = {v: c.iloc[-1] for v, c in abl.items()}
    assert last["full"]["iteration"] == 49
    # smoothed teacher_reward at 49 = base + 0.01 * 47.5 (+ seed offsets, which cancel)
    assert last["full"]["mean"] == pytest.approx(1.475)
    assert last["full"]["n"] == 3
    assert last["full"]["se"] == pytest.approx(0.1 / math.sqrt(3))
    assert last["no_transformer"]["mean"] == pytest.approx(0.8 + 0.475 - 0.1)
    assert math.isnan(last["no_mdn"]["se"]) and last["no_mdn"]["n"] == 1
    assert any("modelfree not used" in n for n in notes)

    base = fig.baseline_data(runs, "seeds", notes)
    clf, mf = base["clf"], base["modelfree"]
    assert list(clf["iteration"]) == [0, 25, 49]  # the teacher eval row is excluded
    assert clf["mean_distance_m"].iloc[-1] == pytest.approx(3.98)
    assert clf["se_distance_m"].iloc[-1] == pytest.approx(0.2 / math.sqrt(3))
    assert mf["mean_distance_m"].iloc[-1] == pytest.approx(2.98)
    assert fig.BASELINE_ERR_MULT * mf["se_distance_m"].iloc[-1] == pytest.approx(0.8)
    pooled = fig.baseline_data(runs, "pooled", [])
    assert pooled["modelfree"]["se_distance_m"].iloc[-1] == pytest.approx(
        math.sqrt(2 * 0.05**2) / 2
    )


def test_combine_rules():
    assert fig.combine([9.5, 10.5], [0.3, 0.4]) == pytest.approx((10.0, 0.5, 2))
    assert fig.combine([8.0], [0.3]) == pytest.approx((8.0, 0.3, 1))
    assert fig.combine([9.5, 10.5], [0.3, 0.4], "pooled") == pytest.approx((10.0, 0.25, 2))
    mean, se, n = fig.combine([1.0, float("nan")], [0.1, 0.2])
    assert (mean, se, n) == (1.0, 0.1, 1)
    assert fig.format_rel(-0.12) == "-12%" and fig.format_rel(0.004) == "+0%"
    assert fig.format_rel(float("nan")) == "n/a"
    assert np.allclose(fig.smooth(pd.Series([0.0, 2.0, 4.0, 6.0]), 2), [0.0, 1.0, 3.0, 5.0])


def test_teacher_only_run_skips_missing_figures(tmp_path):
    run = tmp_path / "teacher_run"
    _make_run(run, "clf", "full", 0, teacher_iters=20, student=False, final=False)
    (run / "config.yaml").write_text(_config_yaml("clf", "full", 0, stage="teacher"))
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = fig.main([str(run), "--target-distance", "100", "--smooth", "1"])
    out = run / "figures"
    assert code == 0
    assert sorted(p.name for p in out.iterdir()) == [
        "runs.csv",
        "runs.md",
        "sample_efficiency.csv",
        "teacher_curves.pdf",
        "teacher_curves.png",
    ]
    text = buf.getvalue()
    assert "note: skip ablation" in text and "note: skip final_metrics" in text
    assert "baseline: skip clf/full (no eval.csv student rows)" in text
    assert "clf: not reached" in text
    assert "runs found: 1 (1 complete, 0 failed, 0 other incomplete)" in text
    eff = pd.read_csv(out / "sample_efficiency.csv")
    assert eff["result"].tolist() == ["not reached"] and eff["iteration"].isna().all()


def test_empty_dir_exits_2(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    proc = subprocess.run(
        [sys.executable, str(SCRIPT), str(empty)], capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1
    assert str(empty) in lines[0] and "no runs found" in lines[0]
    assert "config.yaml" in lines[0]
    assert not (empty / "figures").exists()
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        assert fig.main([str(tmp_path / "missing")]) == 2
    assert err.getvalue().count("is not a directory") == 1


def test_imports_no_simulator():
    tree = ast.parse(SCRIPT.read_text())
    mods = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            mods |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            mods.add(node.module.split(".")[0])
    third_party = mods - set(sys.stdlib_module_names) - {"__future__"}
    assert third_party == {"matplotlib", "numpy", "pandas", "omegaconf"}
    assert len(mods & {"march", "mjlab", "mujoco", "torch", "warp"}) == 0
