"""``analysis/figures.py --terms`` (analysis.term_curves): each panel draws exactly the
metrics.csv columns it names, at the env steps where they have a value."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from analysis.rundirs import load_run
from analysis.term_curves import MARKERS_UP_TO, draw, term_figure
from tests.synthetic_runs import make_run

TEACHER_ITS = 12
STUDENT_ITS = 6


def _lines(ax) -> dict[str, tuple[np.ndarray, np.ndarray, str]]:
    return {
        ln.get_label(): (
            np.asarray(ln.get_xdata(), float),
            np.asarray(ln.get_ydata(), float),
            ln.get_marker(),
        )
        for ln in ax.get_lines()
    }


@pytest.fixture
def run_with_terms(tmp_path):
    """A run whose per-term columns are known functions of the iteration; ``termination/tilt``
    has a value at one iteration only (no other iteration ended an episode)."""
    d = make_run(tmp_path / "run", "clf", "full", 0, teacher_iters=TEACHER_ITS)
    m = pd.read_csv(d / "metrics.csv")
    m = m[(m["stage"] == "teacher") | (m["iteration"] < STUDENT_ITS)].copy()
    t = m["stage"] == "teacher"
    s = ~t
    it = m["iteration"].astype(float)
    m.loc[t, "reward/clf"] = 0.1 * it[t]
    m.loc[t, "reward/torque"] = -0.01 * it[t]
    m.loc[t, "termination/time_out"] = 0.25
    m.loc[t & (m["iteration"] == 7), "termination/tilt"] = 0.75
    m.loc[t, "mean_terrain_level"] = 0.5 * it[t]
    m.loc[t, "terrain_level_std"] = 0.2
    m.loc[s, "loss/loss"] = 30.0 - it[s]
    m.loc[s, "loss/nll"] = 29.0 - it[s]
    m.loc[s, "loss/mode_weight_0"] = 0.5 + 0.01 * it[s]
    m.loc[s, "loss/action_error"] = 0.1
    m.to_csv(d / "metrics.csv", index=False)
    return d, m


def test_each_panel_draws_its_columns_at_their_env_steps(run_with_terms):
    d, m = run_with_terms
    fig = term_figure(load_run(d))
    titles = [ax.get_title() for ax in fig.axes]
    assert titles == [
        "teacher: reward per env step (weighted)",
        "teacher: fraction of ended episodes",
        "student: distillation objective",
        "student: student diagnostics (action error, mixture weights, spread)",
        "teacher: curriculum level",
    ]
    teacher = m[m["stage"] == "teacher"]
    student = m[m["stage"] == "student"]
    expected = [
        (teacher, {"clf": "reward/clf", "torque": "reward/torque"}),
        (teacher, {"time_out": "termination/time_out", "tilt": "termination/tilt"}),
        (student, {"loss": "loss/loss", "nll": "loss/nll"}),
        (student, {"mode_weight_0": "loss/mode_weight_0", "action_error": "loss/action_error"}),
    ]
    for ax, (rows, cols) in zip(fig.axes, expected, strict=False):
        lines = _lines(ax)
        assert set(lines) == set(cols), (ax.get_title(), set(lines))
        for label, col in cols.items():
            x, y, _ = lines[label]
            seen = rows[col].notna()
            np.testing.assert_array_equal(x, rows["env_steps"][seen].to_numpy(float))
            np.testing.assert_allclose(y, rows[col][seen].to_numpy(float))
    level = _lines(fig.axes[-1])["mean"]
    np.testing.assert_allclose(level[1], 0.5 * teacher["iteration"].to_numpy(float))


def test_a_value_seen_once_is_a_visible_point_on_the_stage_span(run_with_terms):
    d, m = run_with_terms
    fig = term_figure(load_run(d))
    ax = fig.axes[1]
    x, y, marker = _lines(ax)["tilt"]
    assert x.tolist() == [7 * float(m.loc[m["stage"] == "teacher", "env_steps"].iloc[1])]
    assert y.tolist() == [0.75] and marker == "o"
    steps = m.loc[m["stage"] == "teacher", "env_steps"]
    lo, hi = ax.get_xlim()
    span = steps.max() - steps.min()
    assert (
        steps.min() - 0.05 * span < lo < steps.min()
        and steps.max() < hi < steps.max() + 0.05 * span
    )


def test_long_runs_draw_lines_without_markers(tmp_path):
    n = MARKERS_UP_TO + 5
    d = make_run(tmp_path / "long", "clf", "full", 0, teacher_iters=n, student=False)
    m = pd.read_csv(d / "metrics.csv")
    m["reward/clf"] = np.sin(m["iteration"])
    m.to_csv(d / "metrics.csv", index=False)
    (ax,) = term_figure(load_run(d)).axes
    x, y, marker = _lines(ax)["clf"]
    assert len(x) == n and marker in ("None", "", None)
    assert math.isclose(y[3], math.sin(3))


def test_a_run_without_term_columns_is_named_not_drawn(tmp_path):
    d = make_run(tmp_path / "old", "clf", "full", 0, teacher_iters=5)
    lines = draw([load_run(d)], tmp_path / "figs")
    assert lines == [f"{d}: no per-term columns in metrics.csv (an older run)"]
    assert not (tmp_path / "figs").exists() or not any((tmp_path / "figs").iterdir())
