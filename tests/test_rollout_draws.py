"""march.env.rollout_draws on the real smoke eval env: a rollout's random inputs (domain
randomisation, reset pose, observation noise, depth corruption, the planner's samples) are the
same wherever it sits in a wave; a draw that cannot be keyed is refused in one line; torch's own
samplers are back, untouched, after the evaluation."""

from __future__ import annotations

import pytest
import torch

from march.config.cli import load
from march.env.rollout_draws import UnkeyedDrawError, keyed_draws
from march.evaluation.protocol import start_wave

pytestmark = pytest.mark.sim

SEED = 7


@pytest.fixture(scope="module")
def env():
    from march.env.build import make_env

    e = make_env(load(["compute=smoke", "reward=clf", "compute.eval_num_envs=4"]), "eval")
    yield e
    e.close()


def _wave_inputs(env, first: int) -> dict[str, torch.Tensor]:
    """What the env's rows start wave ``first`` with: the randomised model fields, the reset
    state, the noisy first observation, the reference plan; then one zero-action step's
    observation (before any foot reaches the ground: the physics is the same in every batch)."""
    with keyed_draws(env, SEED) as draws:
        start_wave(env, draws, first)
        obs, _ = env.reset()
        model, data = env.sim.model, env.sim.data
        term = env.command_manager.get_term("reference")
        out = {
            "body_mass": model.body_mass.clone(),
            "body_ipos": model.body_ipos.clone(),
            "dof_damping": model.dof_damping.clone(),
            "geom_friction": model.geom_friction.clone(),
            "qpos": data.qpos.clone(),
            "qvel": data.qvel.clone(),
            "plan": term.plan_footholds.clone(),
            **{f"obs/{g}": v.clone() for g, v in obs.items()},
        }
        n_act = env.action_manager.total_action_dim
        obs, *_ = env.step(torch.zeros(env.num_envs, n_act))
        out.update({f"step/{g}": v.clone() for g, v in obs.items()})
        # every reward term of that step (the CLF terms read the model's body masses)
        out["step/reward_terms"] = env.reward_manager._step_reward.clone()
    return out


def test_a_rollouts_random_inputs_do_not_depend_on_its_place_in_the_wave(env):
    """Rollouts 0-3 as rows 0-3, then rollouts 2-5 as rows 0-3: rollouts 2 and 3 start with
    the same numbers in rows 2, 3 and in rows 0, 1; other rollouts do not."""
    torch.manual_seed(0)
    state = torch.get_rng_state()
    a = _wave_inputs(env, 0)
    b = _wave_inputs(env, 2)
    assert torch.equal(torch.get_rng_state(), state)  # torch's own stream never drawn
    for name in a:
        assert torch.equal(a[name][2:4], b[name][0:2]), name
    # the numbers are drawn per rollout, not shared: rollout 0 differs from rollout 2 (the same
    # level's cells differ, so compare what does not depend on the course: the model's draws)
    for name in ("body_mass", "geom_friction", "obs/student"):
        assert not torch.equal(a[name][0], a[name][2]), name


def test_an_unkeyable_draw_is_refused_in_one_line_naming_its_caller(env):
    with keyed_draws(env, SEED):
        with pytest.raises(UnkeyedDrawError) as err:
            torch.randperm(env.num_envs)
        assert "torch.randperm" in str(err.value) and "test_rollout_draws.py" in str(err.value)
        with pytest.raises(UnkeyedDrawError) as err:
            torch.rand(env.num_envs + 1, 3)  # not the env batch
        line = str(err.value)
        assert "\n" not in line and f"{env.num_envs + 1} rows" in line
        assert "test_rollout_draws.py" in line
    # outside: torch's samplers are torch's again
    torch.manual_seed(3)
    x = torch.rand(5, 2)
    torch.manual_seed(3)
    assert torch.equal(x, torch.rand(5, 2)) and torch.randperm(4).sort().values.tolist() == [
        0,
        1,
        2,
        3,
    ]


def test_samplers_are_restored_after_an_error_inside(env):
    before = (torch.rand, torch.Tensor.uniform_, env._reset_idx)
    with pytest.raises(ZeroDivisionError), keyed_draws(env, SEED):
        assert torch.rand is not before[0]
        _ = 1 / 0
    assert (torch.rand, torch.Tensor.uniform_) == before[:2]
    assert env._reset_idx == before[2] and not hasattr(env, "rollout_draws")


def test_distribution_samples_are_keyed_by_rollout_too(env):
    """torch.distributions' Normal (torch.normal) and torch.bernoulli, as a stochastic policy
    would draw them: the same rollout's numbers in any row, another rollout's elsewhere."""
    n = env.num_envs

    def draw():
        normal = torch.distributions.Normal(torch.zeros(n, 3), torch.ones(n, 3)).sample()
        coins = torch.bernoulli(torch.full((n, 64), 0.5))
        return normal, coins

    with keyed_draws(env, SEED) as draws:
        draws.streams.assign(SEED, 0)
        a, coins = draw()
        draws.streams.assign(SEED, 2)
        b, coins2 = draw()
    assert torch.equal(a[2:4], b[0:2]) and torch.equal(coins[2:4], coins2[0:2])
    assert not torch.equal(a[0], a[1]) and set(coins.unique().tolist()) == {0.0, 1.0}
    assert 0.3 < coins.mean().item() < 0.7  # 256 fair coins: 6 standard errors either side
