"""Tests for analysis/figures.py on synthetic run directories with known numbers.

The synthetic runs (tests/synthetic_runs.py) plant distinctive values in eval.csv teacher rows,
eval.csv student rows and metrics.csv training rows; these tests check that each figure, its
plotted points (figure_data.csv) and each table carry the evaluation values and never the training
ones, and that the relative differences match hand-computed numbers.
"""

from __future__ import annotations

import ast
import contextlib
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
import synthetic_runs as syn

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "analysis" / "figures.py"
sys.path.insert(0, str(ROOT))  # the analysis package lives at the repo root, beside march/

from analysis import aggregate as agg  # noqa: E402
from analysis import figures as fig  # noqa: E402


def _main(args: list[str]) -> tuple[int, str]:
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = fig.main(args)
    return code, buf.getvalue()


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    root = tmp_path_factory.mktemp("runs")
    base, abl = syn.build_tree(root)
    out = root / "out"
    code, stdout = _main([str(base), str(abl), "--out", str(out), "--smooth", "4"])
    points = pd.read_csv(out / "figure_data.csv")
    return {"base": base, "abl": abl, "out": out, "code": code, "stdout": stdout, "pts": points}


def _pts(tree, figure, panel, series, x_name="iteration"):
    p = tree["pts"]
    sel = p[
        (p["figure"] == figure)
        & (p["panel"] == panel)
        & (p["series"] == series)
        & (p["x_name"] == x_name)
    ]
    return sel.set_index("x")


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
    assert (crashed["teacher_eval_rows"], crashed["student_eval_rows"]) == (3, 0)
    mf = listing[listing["run"] == "sweep_base/2"].iloc[0]
    assert (mf["teacher_eval_rows"], mf["student_eval_rows"]) == (12, 3)
    nostatus = listing[listing["run"] == "sweep_abl/4"].iloc[0]
    assert nostatus["status"] == "incomplete (no status.json)"
    hydra_only = listing[listing["run"] == "sweep_base/1"].iloc[0]
    assert (hydra_only["reward"], hydra_only["seed"]) == ("clf", 1)
    md = (tree["out"] / "runs.md").read_text()
    assert md.count("sweep_abl/3") == 1 and "failed" in md
    out = tree["stdout"]
    assert "sweep_abl/3: failed" in out and "simulated crash" in out
    assert "runs found: 9 (7 complete, 1 failed, 1 other incomplete)" in out


def test_final_table_relative_differences_in_the_papers_convention(tree):
    table = pd.read_csv(tree["out"] / "final_metrics.csv")
    table[["compared_to", "relative"]] = table[["compared_to", "relative"]].fillna("")
    # One row per group: the baseline's clf students (stage all, own teachers) are not pooled
    # with the ablation sweep's clf/full student of a fixed teacher (stage student).
    assert len(table) == 5
    by = {(r.reward, r.variant): r for r in table.itertuples()}
    clf, mf = by[("clf", "full")], by[("modelfree", "full")]
    assert clf.n_runs == 2 and mf.n_runs == 2
    assert by[("clf [stage student]", "full")].n_runs == 1
    assert (clf.n_rollouts, clf.n_torque, clf.n_jerk) == (2 * 64, 2 * 64, 2 * 63)
    assert clf.mean_abs_torque_nm == pytest.approx(8.8) and mf.mean_abs_torque_nm == 10.0
    # SE across seeds: std(8.6, 9.0; ddof=1)/sqrt(2)
    assert clf.se_abs_torque_nm == pytest.approx(0.2)
    assert mf.se_abs_torque_nm == pytest.approx(0.5)
    # (clf - modelfree) / modelfree, by hand from the seed means
    assert clf.compared_to == "modelfree/full"
    assert clf.rel_abs_torque_nm == pytest.approx((8.8 - 10.0) / 10.0)
    assert clf.rel_abs_ang_jerk == pytest.approx((30.5 - 50.0) / 50.0)
    assert clf.rel_distance_m == pytest.approx((4.0 - 3.2) / 3.2)
    # returns of different reward sets are not compared
    assert math.isnan(clf.rel_reward)
    assert clf.relative.startswith(
        "distance +25%, success +100%, torque -12%, jerk -39%, return n/a (different reward sets)"
    )
    assert mf.compared_to == "" and mf.relative == ""
    # (variant - full) / full, clf teacher
    nt, nm = by[("clf [stage student]", "no_transformer")], by[("clf [stage student]", "no_mdn")]
    assert nt.compared_to == nm.compared_to == "clf [stage student]/full"
    assert nt.relative.startswith(
        "distance -10%, success -25%, torque +10%, jerk +20%, return -20%"
    )
    assert nm.relative.startswith(
        "distance -25%, success -50%, torque +25%, jerk +50%, return -40%"
    )
    assert nt.rel_reward == pytest.approx((1.2 - 1.5) / 1.5)
    assert nt.n_runs == 1 and math.isnan(nt.se_abs_torque_nm)  # n=1: no SE across seeds
    md = (tree["out"] / "final_metrics.md").read_text()
    mf_line = next(ln for ln in md.splitlines() if ln.startswith("| modelfree | full |"))
    assert "| 10 ± 0.5 |" in mf_line
    assert (
        "- baseline clf vs modelfree ((clf - modelfree) / modelfree, "
        "student full): distance +25%, success +100%, torque -12%, jerk -39%, return n/a "
        "(different reward sets)" in md
    )
    assert "- ablation no_mdn vs full ((variant - full) / full, clf teacher): distance -25%" in md
    out = tree["stdout"]
    assert "clf (n=2, it 49): distance 4 m, success 80%, torque 8.8 Nm, jerk 30.5 rad/s^3" in out
    assert "  clf vs modelfree: distance +25%, success +100%, torque -12%" in out
    assert "no_transformer (clf [stage student], n=1): reward/step n/a, distance 3.6 m" in out


def test_baseline_plots_student_eval_rows(tree):
    seeds = {"clf": [0, 1], "modelfree": [0, 1]}  # not the ablation's fixed-teacher student
    for reward, ss in seeds.items():
        for key in ("distance_m", "abs_torque_nm", "abs_ang_jerk", "success_rate"):
            pts = _pts(tree, "baseline", key, reward)
            assert list(pts.index) == list(syn.STUDENT_EVAL_ITS)  # no teacher eval row
            for it in syn.STUDENT_EVAL_ITS:
                vals = [syn.student_eval_value(reward, "full", s, key, it) for s in ss]
                assert pts.loc[it, "y"] == pytest.approx(np.mean(vals))
                assert pts.loc[it, "n"] == len(vals)
                se = np.std(vals, ddof=1) / math.sqrt(len(vals))
                assert pts.loc[it, "yerr"] == pytest.approx(4 * se)  # 4 x SE across seeds
    mf = _pts(tree, "baseline", "abs_torque_nm", "modelfree")
    assert mf.loc[49, "y"] == 10.0 and mf.loc[49, "yerr"] == pytest.approx(4 * 0.5)
    # the last student evaluation equals the final table's number
    table = pd.read_csv(tree["out"] / "final_metrics.csv")
    assert table.loc[table["reward"] == "modelfree", "mean_abs_torque_nm"].item() == 10.0


def test_sample_efficiency_reads_teacher_eval_rows(tree):
    eff = pd.read_csv(tree["out"] / "sample_efficiency.csv").fillna(
        {"compared_to": "", "relative": ""}
    )
    by = {r.reward: r for r in eff.itertuples()}
    # seed-mean evaluation distance 0.06 * it (clf), 0.03 * it (modelfree), evaluated every 10
    # iterations; the target is 90% of the better final seed mean (modelfree at 110: 3.3 m),
    # 2.97 m: first reached at 50 (3.0 m) and 100 (3.0 m). Training rows (50 + it m) would
    # give iteration 0.
    assert by["clf"].target_distance_m == pytest.approx(0.9 * 3.3)
    assert (by["clf"].iteration, by["modelfree"].iteration) == (50, 100)
    assert by["clf"].env_steps == 50 * syn.STEPS_PER_IT
    assert by["modelfree"].env_steps == 100 * syn.STEPS_PER_IT
    assert by["clf"].relative == "iterations -50%, env steps -50%"  # (50 - 100) / 100
    assert by["clf"].compared_to == "modelfree"
    assert by["modelfree"].relative == by["modelfree"].compared_to == ""
    assert "sweep_base/1:50" in by["clf"].per_run and "sweep_base/3:100" in by["modelfree"].per_run
    assert "sweep_abl/3:not reached" in by["clf"].per_run  # the crashed run still contributes
    # sweep_abl/4 trained the teacher of seed 1 again: counted once, not twice
    assert "sweep_abl/4" not in by["clf"].per_run
    assert "sweep_abl/4 repeats the teacher of seed 1" in tree["stdout"]
    assert "eval.csv teacher rows" in by["clf"].source
    clf = _pts(tree, "sample_efficiency", "distance_m", "clf")
    assert list(clf.index) == list(range(0, 60, 10))
    # it 0: three seeds (offsets -0.1, +0.1, 0); 10, 20: three; from 30 on: two
    assert clf.loc[0, "y"] == pytest.approx(0.0) and clf.loc[0, "n"] == 3
    assert clf.loc[10, "y"] == pytest.approx(0.6) and clf.loc[10, "n"] == 3
    assert clf.loc[40, "y"] == pytest.approx(2.4) and clf.loc[40, "n"] == 2
    # 1 x SE across seeds: std(2.3, 2.5; ddof=1) / sqrt(2) = 0.1
    assert clf.loc[40, "yerr"] == pytest.approx(0.1)
    mf = _pts(tree, "sample_efficiency", "distance_m", "modelfree")
    assert list(mf.index) == list(range(0, 120, 10))
    assert tree["pts"].query("figure == 'sample_efficiency'")["y"].max() < 10
    steps = _pts(tree, "sample_efficiency", "distance_m", "modelfree", "env_steps")
    assert list(steps.index) == [it * syn.STEPS_PER_IT for it in range(0, 120, 10)]
    succ = _pts(tree, "sample_efficiency", "success_rate", "clf")
    assert succ.loc[40, "y"] == pytest.approx(2.4 / 4)
    out = tree["stdout"]
    assert "clf: iteration 50 (4.915e+06 env steps)" in out
    assert "modelfree: iteration 100" in out and "clf vs modelfree: iterations -50%" in out


def test_ablation_plots_episode_return_from_student_eval_rows(tree):
    seeds = {"full": [2], "no_transformer": [0], "no_mdn": [0]}  # the fixed teacher's students
    for variant, ss in seeds.items():
        for key in ("reward_per_step", "distance_m", "success_rate"):
            pts = _pts(tree, "ablation", key, variant)
            assert list(pts.index) == list(syn.STUDENT_EVAL_ITS)
            scale = 1 / 50 if key == "reward_per_step" else 1.0
            src = "reward" if key == "reward_per_step" else key
            vals = [scale * syn.student_eval_value("clf", variant, s, src, 49) for s in ss]
            assert pts.loc[49, "y"] == pytest.approx(np.mean(vals))
            assert math.isnan(pts.loc[49, "yerr"])  # n=1: no bar, never the rollout SE
    full = _pts(tree, "ablation", "reward_per_step", "full")
    assert full.loc[49, "y"] == pytest.approx(1.5 / 50) and full.loc[49, "n"] == 1
    abl = tree["pts"].query("figure == 'ablation'")
    assert set(abl["series"]) == {"full", "no_transformer", "no_mdn"}  # no modelfree student
    assert (abl["y"] != syn.TRAIN_TEACHER_REWARD).all() and abl["y"].min() >= 0
    assert "ablation: clf teacher only; student rows of reward modelfree not used" in tree["stdout"]


def test_teacher_curves_stay_a_labelled_training_diagnostic(tree):
    tc = tree["pts"].query("figure == 'teacher_curves' and panel == 'mean_distance_m'")
    assert set(tc["series"]) == {"clf", "modelfree"}
    assert tc["y"].min() >= syn.TRAIN_DISTANCE0  # metrics.csv rows, smoothed
    assert set(tc["x_name"]) == {"env_steps"}


def test_every_figure_written(tree):
    for stem in ("ablation", "baseline", "sample_efficiency", "teacher_curves"):
        png = (tree["out"] / f"{stem}.png").read_bytes()
        assert png[:8] == b"\x89PNG\r\n\x1a\n"
        width, height = struct.unpack(">II", png[16:24])
        assert width > 600 and height > 300
        pdf = (tree["out"] / f"{stem}.pdf").read_bytes()
        assert pdf[:5] == b"%PDF-" and len(pdf) > 1000
    written = [ln for ln in tree["stdout"].splitlines() if ln.startswith("wrote ")]
    assert len(written) == 1 and written[0].startswith("wrote 16 files")


def test_combine_and_relative_rules():
    assert agg.combine([9.5, 10.5], [0.3, 0.4]) == pytest.approx((10.0, 0.5, 2))
    mean, se, n = agg.combine([8.0], [0.3])  # one seed: no SE across seeds (not its rollout SE)
    assert (mean, n) == (8.0, 1) and math.isnan(se)
    assert agg.combine([9.5, 10.5], [0.3, 0.4], "pooled") == pytest.approx((10.0, 0.25, 2))
    mean, se, n = agg.combine([1.0, float("nan")], [0.1, 0.2])
    assert (mean, n) == (1.0, 1) and math.isnan(se)
    assert agg.rel_diff(8.8, 10.0) == pytest.approx(-0.12)
    assert agg.rel_diff(-3.0, -2.0) == pytest.approx(-0.5)  # (value - ref) / |ref|
    assert math.isnan(agg.rel_diff(1.0, 0.0)) and math.isnan(agg.rel_diff(float("nan"), 1.0))
    assert agg.format_rel(-0.12) == "-12%" and agg.format_rel(0.004) == "+0%"
    assert agg.format_rel(-0.3905) == "-39%" and agg.format_rel(1.0) == "+100%"
    assert agg.format_rel(float("nan")) == "n/a"
    assert np.allclose(agg.smooth(pd.Series([0.0, 2.0, 4.0, 6.0]), 2), [0.0, 1.0, 3.0, 5.0])


OLD_EVAL_HEADER = (
    "stage,iteration,env_steps,n_rollouts,mean_distance_m,se_distance_m,mean_success_rate,"
    "se_success_rate,mean_abs_torque_nm,se_abs_torque_nm,mean_abs_ang_jerk,se_abs_ang_jerk\n"
)


def test_missing_rows_are_named_never_a_crash(tmp_path):
    # an older clf run: eval.csv without reward columns, no teacher evaluations at all
    old = syn.make_run(tmp_path / "sweep" / "0", "clf", "full", 0, student=True)
    (old / "eval.csv").write_text(
        OLD_EVAL_HEADER + "student,0,0,64,1.5,0.1,0.2,0.05,9,0.2,40,1\n"
        "student,49,49000,64,3.5,0.1,0.6,0.05,8,0.2,30,1\n"
    )
    summary = json.loads((old / "summary.json").read_text())
    del summary["n_torque"], summary["n_jerk"], summary["mean_reward"], summary["se_reward"]
    (old / "summary.json").write_text(json.dumps(summary))
    # a stage=eval run of a teacher checkpoint: its summary is no student result
    tev = syn.make_run(tmp_path / "sweep" / "1", "clf", "full", 1, stage="eval", student=False)
    summary = json.loads((tev / "summary.json").read_text())
    (tev / "summary.json").write_text(json.dumps({**summary, "stage": "teacher"}))
    out = tmp_path / "out"
    res = fig.analyze([tmp_path / "sweep"], out)
    code, text = _main([str(tmp_path / "sweep"), "--out", str(out)])
    assert code == 0
    notes = res["notes"]
    assert "baseline: modelfree/full has no full-student runs" in notes
    assert any(n.startswith("skip sample_efficiency: no eval.csv teacher rows") for n in notes)
    assert "final_metrics: sweep/1 evaluates a teacher policy; not used" in notes
    assert any("modelfree/full has no complete runs" in n for n in notes)
    assert "note: skip sample_efficiency" in text and "sweep/1 evaluates a teacher" in text
    # the old file loads with the columns it has: distance and torque plotted, return named missing
    base = res["points"].query("figure == 'baseline' and series == 'clf'")
    assert base.query("panel == 'abs_torque_nm'").set_index("x")["y"].to_dict() == {0: 9, 49: 8}
    # no floor columns (written before the standing floor): said, never drawn, never a crash
    assert res["axes_notes"]["baseline"]["distance_m"] == [
        "no data: modelfree (no full-student runs)",
        agg.NO_FLOOR,
    ]
    assert res["axes_notes"]["teacher_curves"]["mean_distance_m"] == [agg.NO_FLOOR]
    assert not (res["points"]["x_name"] == "standing_floor").any()
    assert f"  {agg.NO_FLOOR}" in text and "(standing floor" not in text
    assert f"Standing floor: {agg.NO_FLOOR}." in (out / "final_metrics.md").read_text()
    assert "| none (older run) |" in (out / "final_metrics.md").read_text()
    assert res["axes_notes"]["ablation"]["reward_per_step"] == [
        "no data: no_transformer (no clf runs)",
        "no data: no_mdn (no clf runs)",
        "no mean_reward_per_step for full (no rollout defines it, e.g. none succeeded; or an "
        "older eval.csv)",
    ]
    assert res["points"].query("figure == 'ablation' and panel == 'reward_per_step'").empty
    assert not (out / "sample_efficiency.png").exists()
    assert {"baseline.png", "ablation.png", "teacher_curves.png"} <= {p.name for p in out.iterdir()}
    table = pd.read_csv(out / "final_metrics.csv", keep_default_na=False)
    assert table[["reward", "variant", "relative"]].values.tolist() == [["clf", "full", ""]]
    assert table["n_jerk"].tolist() == [""] and table["mean_reward"].tolist() == [""]


def test_teacher_only_run(tmp_path):
    run = syn.make_run(
        tmp_path / "teacher_run", "clf", "full", 0, stage="teacher", student=False, final=False
    )
    code, text = _main([str(run), "--target-distance", "100", "--smooth", "1"])
    out = run / "figures"
    assert code == 0
    assert sorted(p.name for p in out.iterdir()) == [
        "claims.csv",
        "claims.md",
        "figure_data.csv",
        "runs.csv",
        "runs.md",
        "sample_efficiency.csv",
        "sample_efficiency.pdf",
        "sample_efficiency.png",
        "teacher_curves.pdf",
        "teacher_curves.png",
    ]
    assert "note: skip ablation" in text and "note: skip final_metrics" in text
    assert "note: skip baseline" in text
    assert "note: sample_efficiency: modelfree has no runs" in text
    assert "note: sample_efficiency: no arm reaches 100 m" in text
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


def test_script_runs_from_anywhere(tmp_path):
    """`python analysis/figures.py` as a user runs it, from another working directory."""
    run = syn.make_run(
        tmp_path / "r", "modelfree", "full", 0, stage="teacher", student=False, final=False
    )
    proc = subprocess.run(
        [sys.executable, str(SCRIPT), str(run), "--out", str(tmp_path / "o")],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr
    # the target: 90% of its final distance (0.03 * 110 - 0.1 = 3.2 m), 2.88 m, first at 100
    assert "modelfree: iteration 100" in proc.stdout
    assert (tmp_path / "o" / "sample_efficiency.png").is_file()


def test_imports_no_simulator():
    mods = set()
    for path in SCRIPT.parent.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                mods |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module:
                mods.add(node.module.split(".")[0])
    third_party = mods - set(sys.stdlib_module_names) - {"__future__", "analysis"}
    # scipy: t quantiles of the intervals (march.stats); a dependency of march already;
    # march: only its standard-library modules (strict JSON, a run's status), checked below
    assert third_party == {"matplotlib", "numpy", "pandas", "omegaconf", "scipy", "march"}
    assert len(mods & {"mjlab", "mujoco", "torch", "warp"}) == 0
    # what importing the analysis loads, for real: no simulator, no torch
    code = (
        "import sys; sys.path.insert(0, sys.argv[1]);"
        "import analysis.figures, analysis.signal;"
        "print(sorted({m.split('.')[0] for m in sys.modules} & "
        "{'torch', 'mjlab', 'mujoco', 'warp', 'mujoco_warp'}))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code, str(SCRIPT.parent.parent)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]", out.stdout


def test_every_arm_found_is_drawn_in_a_colour_of_its_own(tmp_path):
    """A new arm gets the first palette colour no other arm has (never clf's blue); a clash
    between two configured colours is noted and resolved; only arms a sweep asked for are
    noted as missing."""
    from analysis import arms

    sweep = tmp_path / "sweep"
    syn.make_run(sweep / "0", "clf", "full", 0, student=True)
    new = syn.make_run(sweep / "1", "clf", "full", 1, student=True)
    # an arm the repository does not know, with clf's own colour in its config
    cfg = (new / "config.yaml").read_text().replace("name: clf", "name: mine\n  color: tab:blue")
    (new / "config.yaml").write_text(cfg)
    (sweep / "multirun.yaml").write_text(
        "hydra:\n  mode: MULTIRUN\n  sweeper:\n    params:\n      reward: clf,mine,ghost\n"
    )
    res = fig.analyze([sweep], tmp_path / "out", compare=["mine:clf"])
    comp = res["comparisons"]
    colors = {n: s.color for n, s in comp.arms.items()}
    assert colors["clf"] == "tab:blue"  # the repository's colour for clf
    assert colors["mine"] not in set(colors.values()) - {colors["mine"]}
    assert colors["mine"] == next(c for c in arms.PALETTE if c not in {"tab:blue", "tab:red"})
    assert "reward mine: colour tab:blue is taken; drawn in another" in res["notes"]
    assert set(res["points"].query("figure == 'baseline'")["series"]) == {"clf", "mine"}
    missing = [n for n in res["notes"] if n.startswith("baseline:")]
    assert missing == ["baseline: ghost/full has no full-student runs"]  # not modelfree
    table = res["final"].set_index("reward")
    assert table.loc["mine", "compared_to"] == "clf/full"
    want = (syn.FINAL[("clf", "full", 1)][0] - 3.8) / 3.8  # mine (seed 1) vs clf (seed 0)
    assert table.loc["mine", "rel_distance_m"] == pytest.approx(want)


def test_compare_flag_is_checked_and_sweep_requests_are_read(tmp_path):
    from analysis import arms

    assert _main([str(tmp_path), "--compare", "clf"])[0] == 2
    assert _main([str(tmp_path), "--compare", "clf:clf"])[0] == 2
    assert arms.parse_pair("a:b") == ("a", "b")
    sweep = tmp_path / "s"
    sweep.mkdir()
    (sweep / "multirun.yaml").write_text(
        "hydra:\n  sweeper:\n    params:\n      +experiment: clf,modelfree\n      student: full,no_cnn\n"
        "  overrides:\n    task: [seed=0]\n"
    )
    got = arms.sweep_requests([sweep])
    assert got == (["clf", "modelfree"], ["full", "no_cnn"])  # arm -> its reward's name


def _floor_lines(monkeypatch) -> dict[str, list[tuple[str, float, str]]]:
    """Record, per figure stem, the standing-floor lines of every panel as drawn (ylabel, y,
    colour), just before the figure is saved and closed."""
    from matplotlib.colors import to_hex

    from analysis import plotting

    drawn: dict[str, list[tuple[str, float, str]]] = {}
    real = plotting.save

    def save(figure, out, stem, written):
        drawn[stem] = [
            (ax.get_ylabel(), float(line.get_ydata()[0]), to_hex(line.get_color()))
            for ax in figure.axes
            for line in ax.get_lines()
            if line.get_gid() == plotting.FLOOR_GID and np.ptp(line.get_ydata()) == 0
        ]
        real(figure, out, stem, written)

    monkeypatch.setattr(plotting, "save", save)
    return drawn


DIST = agg.METRICS["distance_m"][1]  # the distance panels' y label


def test_standing_floor_printed_and_drawn_beside_every_distance(tmp_path, monkeypatch):
    """Floors planted per run (clf seeds 0.03 and 0.05 m, modelfree 0.04 and 0.04): each arm's
    floor is their mean, 0.04 m, the same for both, so every distance panel (baseline, both
    sample-efficiency distance panels, the training diagnostic) draws one black dashed line at
    0.04, and every distance printed has it beside it."""
    drawn = _floor_lines(monkeypatch)
    sweep = tmp_path / "sweep"
    floors = {("clf", 0): 0.03, ("clf", 1): 0.05, ("modelfree", 0): 0.04, ("modelfree", 1): 0.04}
    for i, ((reward, seed), f) in enumerate(floors.items()):
        syn.make_run(sweep / str(i), reward, "full", seed, floor=f)
    out = tmp_path / "out"
    code, text = _main([str(sweep), "--out", str(out)])
    assert code == 0
    black = "#000000"
    assert drawn["baseline"] == [(DIST, pytest.approx(0.04), black)]
    assert drawn["sample_efficiency"] == [(DIST, pytest.approx(0.04), black)] * 2
    assert drawn["ablation"] == [(DIST, pytest.approx(0.04), black)]  # clf's full students
    assert drawn["teacher_curves"] == [("mean distance [m]", pytest.approx(0.04), black)]
    pts = pd.read_csv(out / "figure_data.csv").query("x_name == 'standing_floor'")
    assert set(pts["figure"]) == {"baseline", "sample_efficiency", "ablation", "teacher_curves"}
    clf = pts.query("figure == 'baseline' and series == 'clf'").iloc[0]
    pooled = math.sqrt(2 * syn.FLOOR_SE**2) / 2  # rollout SE of the mean of two floors
    assert (clf["y"], clf["se"], clf["n"]) == (pytest.approx(0.04), pytest.approx(pooled), 2)
    # stdout: the final evaluation and the sample-efficiency lines
    assert "clf (n=2, it 49): distance 4 m (standing floor 0.04 m), success 80%" in text
    assert "modelfree (n=2, it 49): distance 3.2 m (standing floor 0.04 m)" in text
    assert "clf: iteration 50 (4.915e+06 env steps); standing floor 0.04 m" in text
    assert "no standing floor" not in text
    table = pd.read_csv(out / "final_metrics.csv").set_index("reward")
    assert table.loc["clf", "floor_distance_m"] == pytest.approx(0.04)
    assert table.loc["clf", "floor_se_distance_m"] == pytest.approx(pooled)
    md = (out / "final_metrics.md").read_text()
    header = next(ln for ln in md.splitlines() if ln.startswith("| reward |"))
    assert "| distance | standing floor | success |" in header
    clf_line = next(ln for ln in md.splitlines() if ln.startswith("| clf | full |"))
    assert "| 4 ± 0.2 | 0.04 ± 0.005657 |" in clf_line
    eff = pd.read_csv(out / "sample_efficiency.csv").set_index("reward")
    assert eff.loc["modelfree", "floor_distance_m"] == pytest.approx(0.04)
    claims_md = (out / "claims.md").read_text()
    floor_part = claims_md.split("## Standing floor")[1].split("## Not compared")[0]
    assert (
        "- clf / full: teacher evaluations: standing floor 0.04 ± 0.0057 m (zero action, 2 runs, "
        "128 rollouts); final student evaluation: standing floor 0.04 ± 0.0057 m" in floor_part
    )


def test_floors_that_differ_are_drawn_per_group_and_older_runs_named(tmp_path, monkeypatch):
    """clf's floor 0.03 m, modelfree's 0.3 m: one line per arm in its colour; the ablation's
    students (a sweep from before the floor) get none, and the outputs say so."""
    drawn = _floor_lines(monkeypatch)
    sweep = tmp_path / "sweep"
    for i, (reward, f) in enumerate((("clf", 0.03), ("modelfree", 0.3))):
        for seed in (0, 1):
            syn.make_run(sweep / f"{i}{seed}", reward, "full", seed, floor=f)
    abl = tmp_path / "abl"
    syn.make_run(abl / "0", "clf", "full", 2, stage="student")
    syn.make_run(abl / "1", "clf", "no_mdn", 0, stage="student")
    res = fig.analyze([sweep, abl], tmp_path / "out")
    text = fig.report(res, tmp_path / "out")
    blue, red = "#1f77b4", "#d62728"  # tab:blue, tab:red: clf's and modelfree's colours
    want = [(DIST, pytest.approx(0.03), blue), (DIST, pytest.approx(0.3), red)]
    assert drawn["baseline"] == want
    assert drawn["sample_efficiency"] == want * 2
    assert drawn["ablation"] == []  # no floor in those runs: named, not drawn
    assert agg.NO_FLOOR in res["axes_notes"]["ablation"]["distance_m"]
    assert "modelfree (n=2, it 49): distance 3.2 m (standing floor 0.3 m)" in text
    assert "full (clf, n=2): reward/step n/a, distance 4 m (standing floor 0.03 m)" in text
    assert (
        "  no standing floor for full (clf [stage student]), no_mdn (clf [stage student]) "
        "(from before the floor)" in text
    )
    claims_md = (tmp_path / "out" / "claims.md").read_text()
    floor_part = claims_md.split("## Standing floor")[1].split("## Not compared")[0]
    assert "- modelfree / full: teacher evaluations: standing floor 0.3 ± 0.0057 m" in floor_part
    assert "- clf [stage student] / no_mdn: no standing floor (from before the floor)" in floor_part


def test_a_distance_target_at_the_floor_is_named(tmp_path):
    """Floors of 3.0 m (a robot that falls far): the sample-efficiency target, 90% of the
    better final distance (3.3 m) = 2.97 m, is below them: reaching it is no progress, and
    stdout and claims.md say so."""
    sweep = tmp_path / "sweep"
    for i, reward in enumerate(("clf", "modelfree")):
        for seed in (0, 1):
            syn.make_run(sweep / f"{i}{seed}", reward, "full", seed, floor=3.0)
    code, text = _main([str(sweep), "--out", str(tmp_path / "out")])
    assert code == 0
    assert (
        "note: sample_efficiency: the target 2.97 m is at or below the standing floor "
        "(clf 3 m, modelfree 3 m): reaching it is no progress" in text
    )
    claims_md = (tmp_path / "out" / "claims.md").read_text()
    assert (
        "- baseline: the sample-efficiency target 2.97 m is at or below a compared arm's "
        "standing floor (3 m on the teacher evaluations)" in claims_md
    )
