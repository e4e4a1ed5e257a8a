"""One registration path for reward terms, their parameters from config, and what they need
(issue 36, items 2-3).

A term is registered anywhere (here, right after importing ``reward_term``: the spot that used
to fail with ``NameError: _builtin_specs``); ``reward.terms.<name>`` takes a weight or
``{weight, params}``, the params checked against the function's signature in one line; the env
builds the planner because a term needs the reference, not because the arm is called clf; the
termination thresholds live in ``termination`` and an old ``reward.tilt_limit_deg`` still works.
"""

from __future__ import annotations

import pytest
import torch

from march.config import ConfigError
from march.config import terms as registry
from march.config.cli import load
from march.env.rewards import needs_reference, reward_term, reward_terms

SIGMA = 0.37  # set from the YAML below; the term returns it, so the reward is weight * SIGMA
WEIGHT = 2.5


@reward_term("ref_probe", needs=("reference",), sigma=0.1)
def ref_probe(env, sigma: float, command_name: str = "reference") -> torch.Tensor:
    """``sigma`` per env, read through the reference command term (so it needs the planner)."""
    from march.env.reference_command import reference_term

    term = reference_term(env, command_name)
    return torch.full_like(term.stance_anchor[:, 0], sigma)


ARM = [
    "reward=modelfree",
    f"+reward.terms.ref_probe={{weight: {WEIGHT}, params: {{sigma: {SIGMA}}}}}",
]


def test_a_term_registers_anywhere_and_takes_params_from_config():
    cfg = load(["compute=smoke", *ARM])
    registry.check_reward(cfg.reward)
    built = reward_terms(cfg.reward)
    assert built["ref_probe"].weight == WEIGHT
    assert built["ref_probe"].params == {"sigma": SIGMA}
    # a bare weight keeps the registered defaults (old YAMLs)
    assert built["feet_edge_distance"].params == {} and built["alive"].weight == 0.5
    spec = registry.TERMS["ref_probe"]
    assert spec.needs == {"reference"}
    assert spec.parameters() == {"sigma": 0.1, "command_name": "reference"}


@pytest.mark.parametrize(
    "entry,needle",
    [
        ("{weight: 1, params: {sigmaa: 0.2}}", "reward.terms.ref_probe.params: ['sigmaa'] not"),
        ("{weight: 1, params: {sigma: 0.2}, extra: 1}", "unknown keys ['extra']"),
        ("{params: {sigma: 0.2}}", "(no weight)"),
        ("abc", "reward.terms.ref_probe='abc' must be a number"),
    ],
)
def test_bad_term_entries_are_one_line(entry, needle):
    with pytest.raises(ConfigError) as err:
        cfg = load(["compute=smoke", "reward=modelfree", f"+reward.terms.ref_probe={entry}"])
        registry.check_reward(cfg.reward)
    assert needle in str(err.value) and "\n" not in str(err.value), str(err.value)


def test_required_param_and_unknown_term_and_taken_name():
    @reward_term("needs_height")
    def needs_height(env, height: float) -> torch.Tensor:
        return env.scene["robot"].data.root_link_pos_w[:, 2] - height

    cfg = load(["compute=smoke", "reward=modelfree", "+reward.terms.needs_height=1.0"])
    with pytest.raises(ConfigError, match=r"needs \['height'\]; set them in"):
        registry.check_reward(cfg.reward)
    cfg = load(["compute=smoke", "reward=modelfree", "+reward.terms.no_such=1.0"])
    with pytest.raises(ConfigError, match=r"unknown reward term\(s\) \['no_such'\].*extra_modules"):
        registry.check_reward(cfg.reward)
    with pytest.raises(ConfigError, match="exists already"):
        reward_term("clf")(needs_height)
    with pytest.raises(ConfigError, match="unknown need"):
        reward_term("x_probe", needs=("planner",))(needs_height)


def test_needs_decide_the_planner_not_the_name():
    modelfree = load(["compute=smoke", "reward=modelfree"]).reward
    assert not needs_reference(modelfree)
    assert needs_reference(load(["compute=smoke", *ARM]).reward)
    assert needs_reference(load(["compute=smoke", "reward=clf_only"]).reward)
    # the name is a label: clf's terms under another name still need the planner, and
    # reward.name=clf with model-free terms does not
    assert needs_reference(load(["compute=smoke", "reward.name=renamed"]).reward)
    assert not needs_reference(
        load(["compute=smoke", "reward=modelfree", "reward.name=clf"]).reward
    )
    # an observation that needs the reference (the factorial control)
    assert needs_reference(load(["compute=smoke", "+experiment=modelfree_ref"]).reward)


def test_termination_thresholds_moved_and_old_keys_still_work():
    cfg = load(["compute=smoke", "termination.tilt_limit_deg=40"])
    assert cfg.termination.tilt_limit_deg == 40.0
    old = load(["compute=smoke", "reward.tilt_limit_deg=35", "reward.max_foot_drop_m=0.2"])
    assert (old.termination.tilt_limit_deg, old.termination.max_foot_drop_m) == (35.0, 0.2)
    assert old.reward.tilt_limit_deg is None  # carried over, not kept twice
    with pytest.raises(ConfigError, match="moved to termination.tilt_limit_deg; set it there"):
        load(["compute=smoke", "reward.tilt_limit_deg=35", "termination.tilt_limit_deg=40"])


@pytest.mark.sim
def test_an_arm_without_clf_terms_builds_the_planner_for_a_term_that_needs_it():
    from march.env.build import build_env_cfg, make_env

    cfg = load(["compute=smoke", "dr=none", *ARM])
    env_cfg = build_env_cfg(cfg, "teacher", num_envs=2)
    assert "reference" in env_cfg.commands and "planner_infeasible" in env_cfg.terminations
    assert not any(t in env_cfg.rewards for t in ("clf", "dclf", "holonomic_pos"))
    plain = build_env_cfg(load(["compute=smoke", "reward=modelfree"]), "teacher", num_envs=2)
    assert "reference" not in plain.commands

    env = make_env(cfg, "teacher", num_envs=2)
    try:
        env.reset()
        env.step(torch.zeros(env.num_envs, env.action_manager.total_action_dim))
        rm = env.reward_manager
        col = rm.active_terms.index("ref_probe")
        # mjlab stores weight * value per step: the YAML's sigma reached the function
        torch.testing.assert_close(rm._step_reward[:, col], torch.full((2,), WEIGHT * SIGMA))
    finally:
        env.close()
