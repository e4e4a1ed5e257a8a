"""The PPO update's columns (march.learn.update_readout, issue 56) against hand computations.

A constructed Gaussian policy whose mean is linear in the normalised observation (rsl-rl's own
MLPModel with identity activations and its EmpiricalNormalization), a real rsl-rl PPO update over
a rollout it drew, and the closed form of the KL between diagonal Gaussians:

    KL(N(m0, s0) || N(m1, s1)) = sum_j log(s1/s0) + (s0^2 + (m0 - m1)^2) / (2 s1^2) - 1/2

computed here in float64 from the weights, std and normaliser read back after the update, and
the rollout's distributions rebuilt by hand from the normaliser state each step was drawn with.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from rsl_rl.algorithms import PPO
from rsl_rl.models import MLPModel
from rsl_rl.storage import RolloutStorage
from tensordict import TensorDict

from march.learn.update_readout import UpdateReadout, rollout_kl

E, T, D, A = 16, 6, 4, 3  # envs, steps, observation dims, actions
NAMES = ["left_hip_pitch_joint", "waist_yaw_joint", "left_elbow_joint"]  # legs, waist, arms
OBS_MEAN, OBS_STD = 3.0, 2.0


def _obs(g: torch.Generator) -> TensorDict:
    x = OBS_MEAN + OBS_STD * torch.randn(E, D, generator=g)
    return TensorDict({"actor": x, "critic": x}, batch_size=[E])


def _policy(seed: int) -> tuple[MLPModel, MLPModel]:
    torch.manual_seed(seed)
    obs = _obs(torch.Generator().manual_seed(seed))
    groups = {"actor": ["actor"], "critic": ["critic"]}
    actor = MLPModel(
        obs,
        groups,
        "actor",
        A,
        hidden_dims=[D],
        activation="identity",  # the mean is linear in the normalised observation
        obs_normalization=True,
        distribution_cfg={"class_name": "GaussianDistribution", "init_std": 1.0},
    )
    critic = MLPModel(obs, groups, "critic", 1, hidden_dims=[8], obs_normalization=True)
    with torch.no_grad():
        actor.distribution.std_param.copy_(torch.tensor([0.6, 1.0, 1.4]))
        norm = actor.obs_normalizer  # near the data's statistics: a moderate drift per step
        norm._mean.fill_(OBS_MEAN - 1.5)
        norm._var.fill_((OBS_STD * 0.5) ** 2)
        norm._std.fill_(OBS_STD * 0.5)
        norm.count.fill_(E)
    return actor, critic


def _linear(actor: MLPModel) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """(W, b, std, [normaliser mean, normaliser std], eps) of the constructed actor: mean =
    W (x - m) / (s + eps) + b."""
    l0, l1 = actor.mlp[0], actor.mlp[2]
    w0, b0 = l0.weight.detach().double().numpy(), l0.bias.detach().double().numpy()
    w1, b1 = l1.weight.detach().double().numpy(), l1.bias.detach().double().numpy()
    n = actor.obs_normalizer
    stats = np.stack([n.mean.double().numpy(), n.std.double().numpy()])
    std = actor.distribution.std_param.detach().double().numpy()
    return w1 @ w0, w1 @ b0 + b1, std, stats, float(n.eps)


def _mean(x: np.ndarray, lin) -> np.ndarray:
    w, b, _, (m, s), eps = lin
    return ((x - m) / (s + eps)) @ w.T + b


def _kl(m0, s0, m1, s1) -> np.ndarray:
    """Closed form, per sample, summed over the action dims."""
    return (np.log(s1 / s0) + (s0**2 + (m0 - m1) ** 2) / (2 * s1**2) - 0.5).sum(-1)


def _log_prob(a, m, s) -> np.ndarray:
    return (-0.5 * ((a - m) / s) ** 2 - np.log(s) - 0.5 * np.log(2 * np.pi)).sum(-1)


def _rollout(seed: int, **ppo: object) -> tuple[PPO, dict[str, np.ndarray]]:
    """A real rollout of the constructed policy: rsl-rl's act / process_env_step (which
    updates the normalisers after every step). Returns the algorithm and, per stored sample,
    the observation, action and the hand-made mean and std it was drawn with."""
    actor, critic = _policy(seed)
    g = torch.Generator().manual_seed(seed + 1)
    obs = _obs(g)
    storage = RolloutStorage("rl", E, T, obs, [A], "cpu")
    kw = {"num_learning_epochs": 2, "num_mini_batches": 2, "learning_rate": 1e-3} | ppo
    alg = PPO(actor, critic, storage, device="cpu", **kw)
    alg.train_mode()
    xs, acts, means, stds = [], [], [], []
    with torch.inference_mode():
        for _ in range(T):
            lin = _linear(actor)  # the normaliser this step's action is drawn with
            a = alg.act(obs)
            xs.append(obs["actor"].double().numpy())
            acts.append(a.double().numpy())
            means.append(_mean(xs[-1], lin))
            stds.append(np.broadcast_to(lin[2], (E, A)))
            obs = _obs(g)
            rewards = torch.randn(E, generator=g)
            alg.process_env_step(obs, rewards, torch.zeros(E, dtype=torch.long), {})
        alg.compute_returns(obs)
    parts = (xs, acts, means, stds)
    hand = {k: np.concatenate(v) for k, v in zip(("x", "a", "m", "s"), parts, strict=True)}
    return alg, hand


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_kl_columns_match_the_closed_form(seed):
    alg, hand = _rollout(seed, learning_rate=1e-2, schedule="fixed")
    stored_m, stored_s = (p.flatten(0, 1).double().numpy() for p in alg.storage.distribution_params)
    np.testing.assert_allclose(stored_m, hand["m"], rtol=1e-5, atol=1e-5)  # the rebuild is right
    before = copy.deepcopy(alg.actor)
    cols = UpdateReadout(alg, NAMES).update()

    # kl_normaliser: the weights before the update, with the normaliser the rollout left
    lin0 = _linear(before)
    want_norm = _kl(hand["m"], hand["s"], _mean(hand["x"], lin0), lin0[2]).mean()
    # kl_update: the updated weights and std, the same normaliser (the update does not move it)
    lin1 = _linear(alg.actor)
    want_update = _kl(hand["m"], hand["s"], _mean(hand["x"], lin1), lin1[2]).mean()
    assert np.allclose(lin0[3], lin1[3])
    # both parts are there to see: the normaliser's drift, and the update's own move
    moved = _kl(_mean(hand["x"], lin0), lin0[2], _mean(hand["x"], lin1), lin1[2]).mean()
    assert want_norm > 1e-3 and moved > 1e-3, (want_norm, moved)
    assert cols["kl_normaliser"] == pytest.approx(want_norm, rel=1e-4)
    assert cols["kl_update"] == pytest.approx(want_update, rel=1e-4)
    # the std columns: the updated std per group (one joint each here) and over every joint
    assert [cols[f"action_std_{g}"] for g in ("legs", "waist", "arms")] == pytest.approx(lin1[2])
    assert cols["action_std"] == pytest.approx(lin1[2].mean())


def test_rollout_kl_is_zero_for_the_policy_that_drew_the_rollout():
    alg, _ = _rollout(5)
    st = alg.storage
    # the stored distributions replaced by the actor's own on the stored observations (with
    # the normaliser as it is now): the KL of a policy from itself is 0
    actor = alg.actor
    with torch.inference_mode():
        st.distribution_params = tuple(
            p.clone()
            for p in (
                actor.mlp(actor.get_latent(st.observations.flatten(0, 1))).view(T, E, A),
                actor.distribution.std_param.detach().expand(T, E, A),
            )
        )
    assert float(rollout_kl(actor, st)) == pytest.approx(0.0, abs=1e-10)


def test_clip_fraction_matches_a_hand_count():
    """One epoch, one mini-batch: the only step sees the policy of before the update with the
    rollout's normaliser; its clip fraction is the share of samples whose ratio of the
    hand-computed densities leaves [0.8, 1.2]."""
    alg, hand = _rollout(3, num_learning_epochs=1, num_mini_batches=1)
    lin0 = _linear(alg.actor)
    cols = UpdateReadout(alg, NAMES).update()
    new = _log_prob(hand["a"], _mean(hand["x"], lin0), lin0[2])
    old = _log_prob(hand["a"], hand["m"], hand["s"])
    want = float((np.abs(np.exp(new - old) - 1.0) > 0.2).mean())
    assert 0.05 < want < 0.95  # neither none nor all: the count is informative
    assert cols["clip_fraction"] == pytest.approx(want, abs=1e-6)


def test_learning_rate_columns_follow_the_schedule_by_hand():
    """rsl-rl's adaptive schedule multiplies the rate by 1.5 before each step while the KL is
    below desired_kl / 2 (capped at 1e-2) and divides it by 1.5 above 2 x desired_kl (floored at
    1e-5); fixed keeps it. 2 epochs x 2 mini-batches = 4 steps."""
    lr0 = 1e-3
    up = [min(1e-2, lr0 * 1.5**k) for k in range(1, 5)]
    down = [max(1e-5, lr0 / 1.5**k) for k in range(1, 5)]
    for kw, lrs in (
        ({"schedule": "fixed"}, [lr0] * 4),
        ({"desired_kl": 1e3}, up),  # every KL far below: raised at every step
        ({"desired_kl": 1e-9}, down),  # every KL far above: cut at every step
    ):
        alg, _ = _rollout(4, learning_rate=lr0, **kw)
        cols = UpdateReadout(alg, NAMES).update()
        assert cols["lr_mean"] == pytest.approx(sum(lrs) / 4), kw
        assert (cols["lr_min"], cols["lr_max"]) == pytest.approx((min(lrs), max(lrs))), kw
        assert alg.learning_rate == pytest.approx(lrs[-1])  # the end value the old column had


def test_the_storage_generator_is_put_back():
    alg, _ = _rollout(6)
    UpdateReadout(alg, NAMES).update()
    assert "mini_batch_generator" not in vars(alg.storage)
    assert not alg.optimizer._optimizer_step_pre_hooks  # the hook is removed
