"""CLF diagnostics (march.clf.diagnostics) against hand-derived values.

P of a double integrator with Q = diag(q1, q2), R = r solves the CARE in closed form:
b = sqrt(q1 r), c = sqrt(r (q2 + 2 b)), a = b c / r, P = [[a, b], [b, c]]. With it every V,
Vmax = lambda_max(P) eta_max^2, per-output term and share below is computed by hand (numpy on the
closed form), never by the code under test.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from march.clf.diagnostics import (
    ClfStats,
    columns,
    histogram_edges,
    output_terms,
    quantiles_from_histogram,
)
from march.clf.lyapunov import ClfCfg, ClfModel

RELATIVE_BIN = 10 ** (1 / 100) - 1  # one histogram bin's relative width (2.3 %)


def closed_form_p(q1: float, q2: float, r: float) -> np.ndarray:
    b = math.sqrt(q1 * r)
    c = math.sqrt(r * (q2 + 2 * b))
    return np.array([[b * c / r, b], [b, c]])


@pytest.fixture(scope="module")
def model() -> ClfModel:
    return ClfModel(ClfCfg())


@pytest.fixture(scope="module")
def blocks(model) -> list[np.ndarray]:
    return [closed_form_p(o.q_pos, o.q_vel, o.r) for o in model.cfg.outputs]


def hand_vmax(blocks, eta_max: float) -> float:
    return max(np.linalg.eigvalsh(p)[-1] for p in blocks) * eta_max**2


def hand_terms(blocks, eta: np.ndarray, etadot: np.ndarray) -> np.ndarray:
    """(E, n) 1/2 x_i^T P_i x_i by the closed form."""
    out = np.zeros_like(eta)
    for i, p in enumerate(blocks):
        out[:, i] = 0.5 * (p[0, 0] * eta[:, i] ** 2 + 2 * p[0, 1] * eta[:, i] * etadot[:, i])
        out[:, i] += 0.5 * p[1, 1] * etadot[:, i] ** 2
    return out


def products(model, eta: np.ndarray, etadot: np.ndarray) -> torch.Tensor:
    """What the env computes: y = eta + y_ref with y_ref = 0 (no angle wraps: |eta| < pi)."""
    y = torch.tensor(eta, dtype=torch.float32)
    ydot = torch.tensor(etadot, dtype=torch.float32)
    zeros = torch.zeros_like(y)
    angles = torch.zeros(y.shape[-1], dtype=torch.bool)
    return model.products_of_outputs(y, ydot, zeros, zeros, angles)


def test_vmax_and_output_terms_match_the_closed_form(model, blocks):
    assert model.v_max == pytest.approx(hand_vmax(blocks, model.cfg.eta_max), rel=1e-9)
    rng = np.random.default_rng(0)
    for _ in range(20):  # generated cases: random errors in random subsets of outputs
        e, n = 16, len(blocks)
        eta = rng.normal(0, 0.1, (e, n)) * (rng.random((e, n)) < 0.3)
        etadot = rng.normal(0, 0.3, (e, n)) * (rng.random((e, n)) < 0.3)
        prod = products(model, eta, etadot)
        terms = output_terms(prod).double().numpy()
        np.testing.assert_allclose(terms, hand_terms(blocks, eta, etadot), rtol=2e-5, atol=1e-7)
        np.testing.assert_allclose(prod.sum(-1).double().numpy(), terms.sum(-1), rtol=1e-5)


def test_quantiles_saturation_validity_and_shares(model, blocks):
    """E envs, each with an error in com_x alone sized so that V/Vmax is a chosen ratio; half the
    envs also carry a swing_z error. Quantiles, saturation and shares against numpy."""
    n = len(blocks)
    names = model.cfg.output_names
    vmax = hand_vmax(blocks, model.cfg.eta_max)
    i_com, i_sw = names.index("com_x"), names.index("swing_z")
    rng = np.random.default_rng(1)
    stats = ClfStats(names, model.v_max, "cpu")
    all_ratios, all_shares, valid_count, samples = [], [], 0, 0
    for _ in range(30):
        e = 40
        ratio = np.exp(rng.uniform(np.log(0.01), np.log(5.0), e))
        eta = np.zeros((e, n))
        eta[:, i_com] = np.sqrt(2 * ratio * vmax / blocks[i_com][0, 0])
        half = np.arange(e) % 2 == 0
        eta[half, i_sw] = 0.01
        etadot = np.zeros((e, n))
        terms = hand_terms(blocks, eta, etadot)
        v = terms.sum(1)
        valid = rng.random(e) < 0.7
        prod = products(model, eta, etadot)
        v_t = prod.sum(-1)
        stats.add(v_t, output_terms(prod), torch.tensor(valid))
        all_ratios.append(v / vmax)
        all_shares.append(terms / v[:, None])
        valid_count += valid.sum()
        samples += e
    row = stats.pop()
    ratios = np.concatenate(all_ratios)
    for name, q in (("v_p10", 0.1), ("v_p50", 0.5), ("v_p90", 0.9)):
        lo, hi = np.quantile(ratios, q, method="inverted_cdf"), np.quantile(ratios, q)
        assert lo * (1 - 2 * RELATIVE_BIN) <= row[f"clf/{name}"] <= hi * (1 + 2 * RELATIVE_BIN)
    assert row["clf/saturated"] == pytest.approx((ratios >= 1).mean(), abs=1e-9)
    assert row["clf/dvdt_valid"] == pytest.approx(valid_count / samples)
    assert row["clf/samples"] == samples
    shares = np.concatenate(all_shares).mean(0)
    got = np.array([row[f"clf/share/{k}"] for k in names])
    np.testing.assert_allclose(got, shares, atol=1e-5)
    assert got.sum() == pytest.approx(1.0, abs=1e-5)
    assert list(row) == columns(names)
    # popped: the next interval starts empty
    empty = stats.pop()
    assert math.isnan(empty["clf/v_p50"]) and empty["clf/samples"] == 0


def test_active_mask_and_zero_v(model, blocks):
    """Inactive envs add nothing; V = 0 lands in the underflow bin (quantile 0) and is left out of
    the shares (0/0)."""
    names = model.cfg.output_names
    stats = ClfStats(names, model.v_max, "cpu")
    e, n = 10, len(names)
    eta = np.zeros((e, n))
    eta[:5, 0] = 1.0  # huge: V >> Vmax
    prod = products(model, eta, np.zeros((e, n)))
    active = torch.tensor([True] * 3 + [False] * 2 + [True] * 5)
    stats.add(prod.sum(-1), output_terms(prod), torch.ones(e, dtype=torch.bool), active)
    row = stats.pop()
    assert row["clf/samples"] == 8
    assert row["clf/saturated"] == pytest.approx(3 / 8)
    assert row["clf/v_p10"] == 0.0  # 5 of 8 at V = 0
    assert row["clf/v_p90"] > 1.0
    assert row[f"clf/share/{names[0]}"] == pytest.approx(1.0)


def test_histogram_quantiles_on_constructed_counts():
    edges = histogram_edges()
    counts = [0.0] * (len(edges) + 1)
    counts[0] = 2  # two zeros
    k = int(np.searchsorted(edges.numpy(), 1.0, side="right"))  # the bin that starts at 1.0
    counts[k] = 6
    counts[-1] = 2  # two beyond RATIO_MAX
    q10, q50, q95 = quantiles_from_histogram(counts, edges, [0.1, 0.5, 0.95])
    assert q10 == 0.0 and q95 == math.inf
    lo, hi = float(edges[k - 1]), float(edges[k])
    assert lo <= q50 <= hi and lo == pytest.approx(1.0, rel=1e-9)
    assert q50 == pytest.approx(lo + (hi - lo) * (5 - 2) / 6)


def test_a_wrong_vmax_is_caught(model, blocks):
    """The planted fault the saturation test must see: Vmax off by 2x moves the saturated share."""
    names = model.cfg.output_names
    n, e = len(names), 100
    vmax = hand_vmax(blocks, model.cfg.eta_max)
    ratio = np.linspace(0.02, 2.0, e)
    eta = np.zeros((e, n))
    eta[:, 0] = np.sqrt(2 * ratio * vmax / blocks[0][0, 0])
    prod = products(model, eta, np.zeros((e, n)))
    right = ClfStats(names, model.v_max, "cpu")
    wrong = ClfStats(names, 2 * model.v_max, "cpu")
    for s in (right, wrong):
        s.add(prod.sum(-1), output_terms(prod), torch.ones(e, dtype=torch.bool))
    expected = (ratio >= 1).mean()
    assert right.pop()["clf/saturated"] == pytest.approx(expected, abs=0.011)
    assert wrong.pop()["clf/saturated"] != pytest.approx(expected, abs=0.011)


def test_share_groups_cover_every_output_once(model):
    """figures --terms sums the 29 output shares into 5 groups: every output in exactly one (the
    group sums equal the total on generated rows), CoM = the three com_ outputs."""
    import pandas as pd

    from analysis.term_curves import share_groups

    names = model.cfg.output_names
    rng = np.random.default_rng(4)
    raw = rng.random((12, len(names)))
    shares = raw / raw.sum(1, keepdims=True)
    rows = pd.DataFrame(shares, columns=[f"clf/share/{n}" for n in names])
    groups = share_groups(rows)
    assert len(groups) == 5
    total = sum(groups.values())
    np.testing.assert_allclose(total.to_numpy(), 1.0, atol=1e-12)
    com = [names.index(k) for k in ("com_x", "com_y", "com_z")]
    np.testing.assert_allclose(groups["CoM"].to_numpy(), shares[:, com].sum(1))
    sw = [names.index(k) for k in ("swing_roll", "swing_pitch", "swing_yaw")]
    np.testing.assert_allclose(groups["swing orientation"].to_numpy(), shares[:, sw].sum(1))


def test_the_sums_of_two_processes_pool_to_the_columns_of_all_their_samples():
    """An evaluation over 2 ranks: each rank's raw sums added give the columns of one meter fed
    every sample (quantiles of the pooled histogram); the mean of the two ranks' quantiles,
    what was logged before, is another number."""
    from march.clf.diagnostics import ClfStats

    names = ["a", "b", "c"]
    gen = torch.Generator().manual_seed(0)
    ranks = [ClfStats(names, 2.0, "cpu") for _ in range(2)]
    whole = ClfStats(names, 2.0, "cpu")
    for r, scale in enumerate((0.1, 10.0)):  # one rank's V small, the other's large
        for _ in range(20):
            terms = torch.rand(16, 3, generator=gen) * scale
            v = terms.sum(-1)
            valid = torch.rand(16, generator=gen) > 0.3
            ranks[r].add(v, terms, valid)
            whole.add(v, terms, valid)
    parts = [s.pop_sums() for s in ranks]
    pooled = ranks[0].row([sum(x) for x in zip(*parts, strict=True)])
    direct = whole.pop()
    assert pooled.keys() == direct.keys()
    for key, value in direct.items():
        assert pooled[key] == pytest.approx(value, rel=1e-12), key
    alone = [ranks[0].row(p) for p in parts]
    mean_p50 = (alone[0]["clf/v_p50"] + alone[1]["clf/v_p50"]) / 2
    assert abs(mean_p50 - direct["clf/v_p50"]) > 0.1 * direct["clf/v_p50"]


@pytest.mark.sim
def test_the_live_meter_reads_what_the_reward_sees(blocks):
    """The meter as wired into a real env (march.env.clf_meter on the smoke clf teacher env,
    random actions): its columns against a hand computation from the env's own state at each
    step, taken right after the reward manager (where the meter reads): eta = y_sim - y_ref at
    tau + dt (angles wrapped), each output's term 1/2 x_i^T P_i x_i with the closed-form P,
    Vmax = lambda_max(P) eta_max^2 by hand. A wrong Vmax or a scaled share in the meter's
    wiring fails here (planted: Vmax x2, shares x0.9)."""
    from march.config.cli import load as load_cfg
    from march.env.build import make_env
    from march.env.clf_meter import pop_clf
    from march.env.reference_command import reference_term
    from march.reference.trajectory import tracking_error

    cfg = load_cfg(["compute=smoke", "compute.num_envs=8", "+experiment=clf"])
    env = make_env(cfg, "teacher")
    try:
        assert getattr(env, "clf_meter", None) is not None
        term = reference_term(env)
        eta_max = term.clf.cfg.eta_max
        vmax = hand_vmax(blocks, eta_max)
        seen: list[tuple[np.ndarray, np.ndarray]] = []  # (V the reward used, hand terms)
        rm = env.reward_manager
        inner = rm.compute  # mjlab's compute, wrapped by the meter

        def watched(dt: float) -> torch.Tensor:
            out = inner(dt)
            sim_pos, sim_vel = term.measured()
            ref_pos, ref_vel = term.reference(term.tau + env.step_dt)
            eta = tracking_error(sim_pos, ref_pos, term.mask).double().numpy()
            etadot = (sim_vel - ref_vel).double().numpy()
            seen.append((term.v.double().numpy().copy(), hand_terms(blocks, eta, etadot)))
            return out

        rm.compute = watched
        env.reset()
        pop_clf(env)  # the reset's samples, if any, are not this test's
        seen.clear()
        g = torch.Generator().manual_seed(0)
        n_act = env.action_manager.total_action_dim
        for _ in range(30):
            env.step(0.3 * torch.randn(env.num_envs, n_act, generator=g))
        row = pop_clf(env)
    finally:
        env.close()
    v = np.concatenate([s[0] for s in seen])
    terms = np.concatenate([s[1] for s in seen])
    np.testing.assert_allclose(terms.sum(-1), v, rtol=1e-3, atol=1e-6)  # the V the reward used
    ratio = np.sort(v / vmax)
    n = len(ratio)
    assert row["clf/samples"] == n == 30 * 8
    assert row["clf/saturated"] == pytest.approx((v >= vmax).mean(), abs=0.5 / n)
    for name, q in (("clf/v_p10", 0.1), ("clf/v_p50", 0.5), ("clf/v_p90", 0.9)):
        k = q * n  # the histogram's quantile lies between the order statistics around rank qn
        lo, hi = ratio[max(math.floor(k) - 1, 0)], ratio[min(math.ceil(k), n - 1)]
        assert lo / (1 + RELATIVE_BIN) <= row[name] <= hi * (1 + RELATIVE_BIN), (name, lo, hi)
    positive = v > 0
    share = (terms[positive] / v[positive, None]).mean(0)
    for i, out_name in enumerate(term.clf.cfg.output_names):
        assert row[f"clf/share/{out_name}"] == pytest.approx(share[i], rel=2e-3, abs=1e-6)
