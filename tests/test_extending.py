"""Extending march as docs/extending.md says: a new reward arm in a config tree of your own (one
YAML), a new reward-term function (one decorated function), and nothing else edited. The arm runs
a smoke teacher -> student -> evaluation through ``march.train``, ``march.inspect`` builds its env,
and the figures draw it beside clf in a colour of its own and compare the two (``--compare``).
"""

from __future__ import annotations

import contextlib
import io
import json
import sys
from pathlib import Path

import pandas as pd
import pytest
import synthetic_runs as syn
import torch
from omegaconf import OmegaConf

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from analysis import figures as fig  # noqa: E402
from march.config.registry import options  # noqa: E402
from march.env.rewards import available_terms, reward_term  # noqa: E402

pytestmark = pytest.mark.sim

ARM_YAML = """\
# CLF terms and the regularisers, no holonomic terms, plus an upright bonus.
name: clf_upright
label: CLF upright
terms:
  clf: 10.0
  dclf: 1.0
  torque: 1.0e-5
  joint_limits: 1.0
  action_rate: 0.01
  upright_bonus: 0.5
"""


# The one new function: a reward term (reward-signed, one value per env).
@reward_term("upright_bonus", min_cos=0.9)
def upright_bonus(env, min_cos: float) -> torch.Tensor:
    """1 while the pelvis z axis is within acos(min_cos) of vertical, else 0."""
    gravity_b = env.scene["robot"].data.projected_gravity_b
    return (-gravity_b[:, 2] >= min_cos).float()


QUICK = [
    "compute=smoke",
    "teacher.max_iterations=2",
    "distill.max_iterations=1",
    "env.episode_length_s=0.1",
    "eval.num_rollouts=2",
    "eval.episode_length_s=0.2",  # 10-step rollouts: the plumbing is under test, not the gait
]


def _tool(module, argv: list[str]) -> str:
    """Run ``python -m <module> argv`` in this process (where the new term is registered)."""
    buf = io.StringIO()
    old = sys.argv
    sys.argv = [module.__name__, *argv]
    try:
        with contextlib.redirect_stdout(buf):
            module.main()
    finally:
        sys.argv = old
    return buf.getvalue()


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    root = tmp_path_factory.mktemp("extending")
    conf = root / "my_conf"
    (conf / "reward").mkdir(parents=True)
    (conf / "reward" / "clf_upright.yaml").write_text(ARM_YAML)
    return {"root": root, "search": f"hydra.searchpath=[file://{conf}]", "conf": conf}


def test_the_new_arm_and_term_are_registered(tree):
    assert "upright_bonus" in available_terms()
    arms = {o.name: o for o in options("reward", [ROOT / "conf", tree["conf"]])}
    assert {"clf", "modelfree", "clf_upright"} <= set(arms)
    assert arms["clf_upright"].label == "CLF upright"
    with pytest.raises(Exception, match="exists already"):
        reward_term("clf")(upright_bonus)  # a name means one thing in every arm


def test_inspect_builds_the_new_arm(tree):
    import march.inspect

    text = _tool(march.inspect, [tree["search"], "reward=clf_upright", "compute=smoke"])
    report = json.loads(text[text.index("{") :])
    blob = json.dumps(report)
    assert "upright_bonus" in blob and "clf_upright" in blob
    assert "holonomic_pos" not in blob  # the arm dropped them; nothing else changed


def test_smoke_run_and_figures_compare_it_with_clf(tree, capsys):
    import march.train

    run = tree["root"] / "clf_upright_run"
    # In this process Hydra finds conf/ by path (``python -m march.train`` finds it beside
    # the module); the rest is the command line a user types.
    args = [f"--config-path={ROOT / 'conf'}", tree["search"], "reward=clf_upright", *QUICK]
    _tool(march.train, [*args, f"hydra.run.dir={run}"])
    assert json.loads((run / "status.json").read_text())["state"] == "done"
    summary = json.loads((run / "summary.json").read_text())
    assert summary["n_rollouts"] == 2
    metrics = pd.read_csv(run / "metrics.csv")
    assert (metrics["stage"] == "teacher").sum() == 2
    # the reference arm: a synthetic clf run (tests/synthetic_runs.py) whose config is this
    # run's with the clf reward, so that the two differ in the arms' own field (reward.*)
    # only: every output compares like for like (issue 57)
    ref = syn.make_run(tree["root"] / "clf_run", "clf", "full", 0, student=True)
    cfg = OmegaConf.load(next(run.glob("**/config.yaml")))
    cfg.reward.name = "clf"
    cfg.reward.terms = OmegaConf.load(ROOT / "conf" / "reward" / "clf.yaml").terms
    OmegaConf.save(cfg, ref / "config.yaml")
    out = tree["root"] / "figures"
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = fig.main([str(run), str(ref), "--out", str(out), "--compare", "clf_upright:clf"])
    text = buf.getvalue()
    assert code == 0, text
    res = fig.analyze([run, ref], out, compare=["clf_upright:clf"])
    comp = res["comparisons"]
    assert comp.pairs == [("clf_upright", "clf")]
    colors = {name: s.color for name, s in comp.arms.items()}
    assert colors["clf_upright"] != colors["clf"]
    assert len(set(colors.values())) == len(colors)  # no two arms share a colour
    assert comp.arms["clf_upright"].label == "CLF upright"
    # drawn: both arms in the baseline figure; compared: clf_upright against clf
    base = res["points"].query("figure == 'baseline'")
    assert set(base["series"]) == {"clf_upright", "clf"}
    assert "clf_upright vs clf:" in text and "distance " in text
    table = pd.read_csv(out / "final_metrics.csv", keep_default_na=False)
    row = table[table["reward"] == "clf_upright"].iloc[0]
    assert row["compared_to"] == "clf/full"
    ref_distance = syn.FINAL[("clf", "full", 0)][0]
    want = (summary["mean_distance_m"] - ref_distance) / ref_distance
    assert float(row["rel_distance_m"]) == pytest.approx(want, rel=1e-9, abs=1e-12)
    # modelfree was neither swept nor compared: no "missing" note about it
    assert not any("modelfree" in n for n in res["notes"])
    assert (out / "baseline.png").is_file()
