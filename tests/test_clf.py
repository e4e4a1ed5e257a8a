import math

import numpy as np
import pytest
import torch

from march.clf.lyapunov import (
    CLF_OUTPUT_NAMES,
    ClfCfg,
    ClfModel,
    ClfOutputCfg,
    VHistory,
    backward_difference,
    solve_output_care,
)

torch.set_num_threads(1)

A = np.array([[0.0, 1.0], [0.0, 0.0]])
B = np.array([[0.0], [1.0]])


@pytest.fixture(scope="module")
def model() -> ClfModel:
    return ClfModel(ClfCfg(), dtype=torch.float64)


def test_default_outputs():
    cfg = ClfCfg()
    assert len(cfg.outputs) == 29
    assert CLF_OUTPUT_NAMES[:3] == ("com_x", "com_y", "com_z")
    assert CLF_OUTPUT_NAMES[12] == "waist_yaw_joint"
    by = {o.name: o for o in cfg.outputs}
    assert (by["swing_z"].q_pos, by["swing_z"].q_vel) == (3500.0, 100.0)
    assert (by["swing_x"].q_pos, by["swing_x"].q_vel) == (1500.0, 125.0)
    assert (by["com_x"].q_pos, by["com_x"].q_vel) == (25.0, 200.0)
    assert all(0.01 <= o.r <= 0.1 for o in cfg.outputs)
    assert (cfg.eta_max, cfg.etadot_max, cfg.alpha) == (0.2, 0.3, 0.5)


def test_care_residual_and_positive_definite(model):
    for o, p in zip(model.cfg.outputs, model.P_blocks_np, strict=True):
        q = np.diag([o.q_pos, o.q_vel])
        res = A.T @ p + p @ A - p @ B @ B.T @ p / o.r + q
        scale = np.linalg.norm(q) + np.linalg.norm(p @ B @ B.T @ p / o.r)
        assert np.linalg.norm(res) / scale < 1e-8, o.name
        assert np.allclose(p, p.T)
        assert np.linalg.eigvalsh(p).min() > 0.0, o.name
    # full P: block diagonal, PD, largest eigenvalue = max over blocks
    assert model.P.shape == (58, 58)
    assert np.linalg.eigvalsh(model.P_np).min() > 0.0
    assert model.P_np[0, 2] == 0.0 and model.P_np[1, 3] == 0.0
    blk_max = max(np.linalg.eigvalsh(p)[-1] for p in model.P_blocks_np)
    assert model.lambda_max == pytest.approx(blk_max, rel=1e-12)
    assert model.p_norm == pytest.approx(model.lambda_max, rel=1e-12)


def test_care_closed_form():
    # double integrator: p12 = sqrt(q r), p22 = sqrt(r (qv + 2 p12)), p11 = p12 p22 / r
    p = solve_output_care(3500.0, 100.0, 0.05)
    p12 = math.sqrt(3500.0 * 0.05)
    p22 = math.sqrt(0.05 * (100.0 + 2.0 * p12))
    p11 = p12 * p22 / 0.05
    assert p[0, 1] == pytest.approx(p12, rel=1e-10)
    assert p[1, 1] == pytest.approx(p22, rel=1e-10)
    assert p[0, 0] == pytest.approx(p11, rel=1e-10)
    with pytest.raises(ValueError):
        solve_output_care(1.0, 1.0, 0.0)


def test_value(model):
    g = torch.Generator().manual_seed(0)
    e = torch.randn(64, 29, generator=g, dtype=torch.float64) * 0.1
    ed = torch.randn(64, 29, generator=g, dtype=torch.float64) * 0.3
    v = model.value(e, ed)
    assert v.shape == (64,)
    x = model.state(e, ed)
    v_ref = 0.5 * torch.einsum("bi,ij,bj->b", x, model.P, x)
    assert torch.allclose(v, v_ref, rtol=1e-12, atol=0.0)
    assert bool((v > 0).all())
    zero = torch.zeros(3, 29, dtype=torch.float64)
    assert torch.equal(model.value(zero, zero), torch.zeros(3, dtype=torch.float64))
    # one output only, hand value: V = 1/2 p11 * 0.1^2
    e1 = torch.zeros(1, 29, dtype=torch.float64)
    e1[0, model.index("swing_z")] = 0.1
    p11 = model.P_blocks_np[model.index("swing_z")][0, 0]
    assert model.value(e1, torch.zeros_like(e1)).item() == pytest.approx(0.5 * p11 * 0.01)
    with pytest.raises(ValueError):
        model.value(torch.zeros(2, 28), torch.zeros(2, 28))


def test_normalisers(model):
    lam = model.lambda_max
    assert model.v_max == pytest.approx(lam * 0.04)
    assert model.vdot_max == pytest.approx(2 * lam * 0.2 * 0.3 + 0.5 * lam * 0.04)
    # swing_z dominates: p11 = sqrt(175) sqrt(0.05 (100 + 2 sqrt(175))) / 0.05
    p11 = math.sqrt(175.0) * math.sqrt(0.05 * (100.0 + 2 * math.sqrt(175.0))) / 0.05
    assert lam == pytest.approx(p11, rel=1e-3)


def test_clf_reward(model):
    vm = model.v_max
    v = torch.tensor([0.0, 0.5 * vm, vm, 3.0 * vm, 1e9], dtype=torch.float64)
    r = model.clf_reward(v)
    expect = torch.tensor(
        [1.0, math.exp(-0.5), math.exp(-1), math.exp(-1), math.exp(-1)], dtype=torch.float64
    )
    assert torch.allclose(r, expect, rtol=1e-12)
    assert bool((r >= math.exp(-1) - 1e-15).all() and (r <= 1.0).all())


def test_dclf_reward(model):
    a, vd = model.alpha, model.vdot_max
    v = torch.tensor([10.0, 10.0, 10.0, 10.0, 0.0], dtype=torch.float64)
    vdot = torch.tensor([-5.0, -20.0, 0.0, 30.0, 0.0], dtype=torch.float64)
    r = model.dclf_reward(v, vdot)
    # Vdot = -alpha V exactly -> 0; faster decay -> 0; slower -> negative
    assert r[0].item() == 0.0 and r[1].item() == 0.0 and r[4].item() == 0.0
    assert r[2].item() == pytest.approx(-(a * 10.0) / vd)
    assert r[3].item() == pytest.approx(-(30.0 + a * 10.0) / vd)
    assert bool((r <= 0).all())
    # hand-computed with a one-output model: P = CARE(1, 1, 1)
    one = ClfModel(ClfCfg(outputs=[ClfOutputCfg("y", 1.0, 1.0, 1.0)]), dtype=torch.float64)
    # p12 = 1, p22 = sqrt(1 + 2) = p11: P = [[sqrt3, 1], [1, sqrt3]], lambda_max = 1 + sqrt3
    lam = 1.0 + math.sqrt(3.0)
    assert one.lambda_max == pytest.approx(lam, rel=1e-12)
    vdmax = 2 * lam * 0.2 * 0.3 + 0.5 * lam * 0.04
    assert one.vdot_max == pytest.approx(vdmax)
    r1 = one.dclf_reward(
        torch.tensor([0.1], dtype=torch.float64), torch.tensor([0.05], dtype=torch.float64)
    )
    assert r1.item() == pytest.approx(-(0.05 + 0.5 * 0.1) / vdmax)
    assert r1.item() == pytest.approx(-0.1 / (0.14 * (1.0 + math.sqrt(3.0))), rel=1e-12)
    # validity mask and optional clip
    rv = model.dclf_reward(v, vdot, valid=torch.tensor([True, True, False, True, True]))
    assert rv[2].item() == 0.0 and rv[3].item() == pytest.approx(r[3].item())
    clipped = ClfModel(ClfCfg(dclf_clip=1.0), dtype=torch.float64)
    rc = clipped.dclf_reward(torch.tensor([0.0]), torch.tensor([1e6]))
    assert rc.item() == -1.0


def test_backward_difference_exact_on_quadratic():
    dt = 0.02
    t = torch.tensor([1.0, 2.5, -0.3], dtype=torch.float64)

    def f(s):
        return 3.0 * s**2 - 2.0 * s + 0.7

    d = backward_difference(f(t), f(t - dt), f(t - 2 * dt), dt)
    assert torch.allclose(d, 6.0 * t - 2.0, rtol=0, atol=1e-10)


def test_backward_difference_matches_value_rate(model):
    # linear error trajectory -> V quadratic in t -> 3-point difference is exact
    g = torch.Generator().manual_seed(1)
    e0 = torch.randn(4, 29, generator=g, dtype=torch.float64) * 0.1
    d = torch.randn(4, 29, generator=g, dtype=torch.float64) * 0.2
    dt = 0.02

    def v_at(s):
        return model.value(e0 + s * d, d)

    num = backward_difference(v_at(2 * dt), v_at(dt), v_at(0.0), dt)
    exact = model.value_rate(e0 + 2 * dt * d, d, torch.zeros_like(d))
    assert torch.allclose(num, exact, rtol=1e-9, atol=1e-9)


def test_vhistory_reset_behaviour():
    dt = 0.02
    h = VHistory(3, dt, dtype=torch.float64)

    def f(k):  # V at step k, quadratic in time
        s = k * dt
        return torch.full((3,), 2.0 * s**2 + s + 1.0, dtype=torch.float64)

    vd, ok = h.update(f(0))
    assert torch.equal(vd, torch.zeros(3, dtype=torch.float64)) and not bool(ok.any())
    vd, ok = h.update(f(1))
    assert bool(ok.all())
    assert torch.allclose(vd, (f(1) - f(0)) / dt)  # first-order fallback
    vd, ok = h.update(f(2))
    assert torch.allclose(vd, torch.full((3,), 4.0 * 2 * dt + 1.0, dtype=torch.float64))
    assert h.count.tolist() == [2, 2, 2]
    # reset env 1 (e.g. touchdown reference switch): it restarts, others keep 3-point
    h.reset(torch.tensor([1]))
    assert h.count.tolist() == [2, 0, 2]
    jump = f(3).clone()
    jump[1] += 100.0  # discontinuity in V at the switch must not leak into dV/dt
    vd, ok = h.update(jump)
    assert ok.tolist() == [True, False, True]
    assert vd[1].item() == 0.0
    assert vd[0].item() == pytest.approx(4.0 * 3 * dt + 1.0)
    vd, ok = h.update(f(4) + torch.tensor([0.0, 100.0, 0.0], dtype=torch.float64))
    assert vd[1].item() == pytest.approx((f(4)[1] - f(3)[1]).item() / dt)
    vd, ok = h.update(f(5) + torch.tensor([0.0, 100.0, 0.0], dtype=torch.float64))
    assert torch.allclose(vd, torch.full((3,), 4.0 * 5 * dt + 1.0, dtype=torch.float64))
    h.reset()
    assert h.count.tolist() == [0, 0, 0]
    # bool-mask reset
    h.update(f(0))
    h.reset(torch.tensor([True, False, True]))
    assert h.count.tolist() == [0, 1, 0]


def test_model_to_device_and_float32():
    m = ClfModel()
    assert m.P.dtype == torch.float32 and m.P.device.type == "cpu"
    m.to("cpu")
    e = torch.full((2, 29), 0.05)
    v = m.value(e, torch.zeros_like(e))
    assert v.dtype == torch.float32
    p11 = torch.tensor(m.P_blocks_np[:, 0, 0]).sum().item()
    assert v[0].item() == pytest.approx(0.5 * 0.0025 * p11, rel=1e-5)


def test_structured_config():
    omegaconf = pytest.importorskip("omegaconf")
    c = omegaconf.OmegaConf.structured(ClfCfg)
    assert len(c.outputs) == 29 and c.outputs[8].q_pos == 3500.0 and c.dclf_clip is None
    cfg = omegaconf.OmegaConf.to_object(c)
    assert ClfModel(cfg).num_outputs == 29


def test_value_of_outputs_equals_value_of_the_wrapped_errors():
    """Issue 41: V from the outputs in one product with P (angles wrapped inside) equals
    ClfModel.value of tracking_error's eta, over many random outputs with angles far apart."""
    from march.reference.trajectory import angle_mask, tracking_error

    model = ClfModel(dtype=torch.float64)
    mask = angle_mask(17)
    for seed in range(20):
        g = torch.Generator().manual_seed(seed)
        y, y_ref, yd, yd_ref = (
            4 * torch.rand(13, 29, generator=g, dtype=torch.float64) - 2 for _ in range(4)
        )
        y[:, mask] *= 4.0  # angle errors beyond pi: the wrap matters
        want = model.value(tracking_error(y, y_ref, mask), yd - yd_ref)
        got = model.value_of_outputs(y, yd, y_ref, yd_ref, mask)
        assert torch.allclose(got, want, rtol=1e-12, atol=0.0), seed
    m32 = ClfModel()
    got = m32.value_of_outputs(*(t.float() for t in (y, yd, y_ref, yd_ref)), mask)
    assert torch.allclose(got.double(), want, rtol=1e-5)


def test_history_weights_equal_the_backward_differences():
    """VHistory.update's one weighted sum gives the three-point difference, the first-order one
    after one sample and 0 without history (also for an infinite V)."""
    dt = 0.02
    h = VHistory(4, dt, dtype=torch.float64)
    vs = [
        torch.tensor([1.0, 2.0, 3.0, float("inf")], dtype=torch.float64) * (k + 1) ** 2
        for k in range(3)
    ]
    d0, ok0 = h.update(vs[0])
    assert torch.equal(d0, torch.zeros(4, dtype=torch.float64)) and not ok0.any()
    d1, _ = h.update(vs[1])
    assert torch.allclose(d1[:3], (vs[1] - vs[0])[:3] / dt, rtol=1e-12)
    d2, ok2 = h.update(vs[2])
    want = backward_difference(vs[2], vs[1], vs[0], dt)
    assert torch.allclose(d2[:3], want[:3], rtol=1e-12) and ok2.all()


def test_folded_reward_formulas_equal_the_papers():
    """r_clf and r_dclf with the sign and the normaliser folded into one product (issue 41)
    equal exp(-min(V, Vmax)/Vmax) and -max((Vdot + alpha V)/Vdmax, 0) (clipped, masked) within
    float32 rounding over random V and dV/dt of both signs."""
    g = torch.Generator().manual_seed(3)
    for clip in (None, 1.0):
        model = ClfModel(ClfCfg(dclf_clip=clip))
        v = model.v_max * 3 * torch.rand(500, generator=g)
        vdot = model.vdot_max * 4 * (torch.rand(500, generator=g) - 0.5)
        valid = torch.rand(500, generator=g) > 0.2
        want = -torch.clamp((vdot + model.alpha * v) / model.vdot_max, min=0.0)
        if clip is not None:
            want = want.clamp(min=-clip)
        want = torch.where(valid, want, torch.zeros_like(want))
        assert torch.allclose(model.dclf_reward(v, vdot, valid), want, atol=1e-6, rtol=1e-6)
        clf = torch.exp(-torch.clamp(v, max=model.v_max) / model.v_max)
        assert torch.allclose(model.clf_reward(v), clf, atol=1e-7, rtol=1e-6)
