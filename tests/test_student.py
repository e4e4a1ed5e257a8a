"""Student networks: MDN maths, variants' structure, distillation loss, ONNX parity."""

from __future__ import annotations

import math

import torch

torch.set_num_threads(1)

import numpy as np  # noqa: E402
import onnxruntime as ort  # noqa: E402
import pytest  # noqa: E402
from torch import nn  # noqa: E402
from torch.distributions import Categorical, Independent, MixtureSameFamily, Normal  # noqa: E402

from march.config import STUDENTS, ConfigError, StudentCfg  # noqa: E402
from march.policies import (  # noqa: E402
    MDNHead,
    MDNParams,
    StudentPolicy,
    mdn_log_prob,
    mdn_nll,
    mdn_sample,
    mixture_weights,
    mode_mean,
    squash_log_std,
    top_mode_mean,
)
from march.policies.mdn import unsquash_log_std  # noqa: E402

P, HIST, CMD, HW, A = 10, 5, 3, (24, 32), 4


PARTS = ("image", "fusion", "head")


def registered_parts(variant: str) -> dict[str, str]:
    """The parts ``conf/student/<variant>.yaml`` states (march.config.registry)."""
    from march.config.registry import options

    data = next((o.data for o in options("student") if o.name == variant), {})
    return {k: data[k] for k in PARTS if k in data}


def small_cfg(variant: str, **kw) -> StudentCfg:
    kw = {**registered_parts(variant), **kw}
    return StudentCfg(
        variant=variant,
        cnn_channels=(4, 8),
        cnn_kernels=(3, 3),
        cnn_strides=(2, 2),
        d_model=32,
        n_heads=4,
        n_layers=1,
        dim_feedforward=64,
        fusion_mlp=(64,),
        head_hidden=(32,),
        **kw,
    )


def small_policy(variant: str, seed: int = 0, **kw) -> StudentPolicy:
    torch.manual_seed(seed)
    return StudentPolicy(small_cfg(variant, **kw), P, HIST, CMD, HW, A)


def inputs(batch: int, seed: int = 1) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return (
        torch.randn(batch, HIST, P, generator=g),
        torch.randn(batch, CMD, generator=g),
        3.0 * torch.rand(batch, 1, *HW, generator=g),
    )


def random_params(b: int, k: int, a: int, seed: int = 0) -> MDNParams:
    g = torch.Generator().manual_seed(seed)
    return MDNParams(
        torch.randn(b, k, generator=g, dtype=torch.float64),
        torch.randn(b, k, a, generator=g, dtype=torch.float64),
        0.5 * torch.randn(b, k, a, generator=g, dtype=torch.float64),
    )


def torch_mixture(params: MDNParams) -> MixtureSameFamily:
    return MixtureSameFamily(
        Categorical(logits=params.logits),
        Independent(Normal(params.means, params.log_std.exp()), 1),
    )


# ----------------------------------------------------------------------------- MDN maths
def test_log_prob_matches_torch_mixture():
    params = random_params(6, 3, 5)
    ref = torch_mixture(params)
    g = torch.Generator().manual_seed(3)
    a1 = torch.randn(6, 5, generator=g, dtype=torch.float64)
    a8 = torch.randn(6, 8, 5, generator=g, dtype=torch.float64)
    lp1 = mdn_log_prob(params, a1)
    lp8 = mdn_log_prob(params, a8)
    assert lp1.shape == (6,) and lp8.shape == (6, 8)
    torch.testing.assert_close(lp1, ref.log_prob(a1), atol=1e-5, rtol=0)
    torch.testing.assert_close(lp8, ref.log_prob(a8.transpose(0, 1)).T, atol=1e-5, rtol=0)
    # float32 agrees too, and the NLL is the mean negative log-prob over samples and batch
    p32 = MDNParams(*(t.float() for t in params))
    torch.testing.assert_close(mdn_log_prob(p32, a8.float()).double(), lp8, atol=1e-4, rtol=0)
    assert mdn_nll(params, a8).item() == pytest.approx(-lp8.mean().item(), abs=1e-12)


def test_log_prob_numerically_stable_far_from_modes():
    params = random_params(4, 2, 3)
    p32 = MDNParams(*(t.float() for t in params))
    far = torch.full((4, 3), 1e3)
    lp = mdn_log_prob(p32, far)
    assert torch.isfinite(lp).all()
    # far away the log-density is that of the best mode alone (naive sum of exp underflows to -inf)
    comp = Independent(Normal(p32.means, p32.log_std.exp()), 1).log_prob(far.unsqueeze(1))
    best = (torch.log_softmax(p32.logits, -1) + comp).max(-1).values
    torch.testing.assert_close(lp, best, rtol=1e-6, atol=1e-2)
    assert lp.max().item() < -1e4


def test_top_mode_and_mode_mean():
    params = random_params(32, 3, 4, seed=5)
    heaviest = mixture_weights(params).argmax(-1)
    top = top_mode_mean(params)
    assert top.shape == (32, 4)
    expected = params.means[torch.arange(32), heaviest]
    assert torch.equal(top, expected)
    assert len(set(heaviest.tolist())) == 3  # every mode is the top one for some row
    for k in range(3):
        assert torch.equal(mode_mean(params, k), params.means[:, k])


def test_log_std_range_and_min_std_on_extreme_raw_outputs():
    head = MDNHead(8, 3, num_modes=2, min_std=1e-3, log_std_min=-3.0, log_std_max=2.0)
    raw_logits = torch.zeros(4, 2)
    raw_means = torch.zeros(4, 6)
    raw = torch.tensor(
        [[-1e30, -1e6, -50.0, -3.5, -3.0, 0.0], [1.0, 2.0, 2.5, 40.0, 1e6, 1e30]]
    ).repeat(2, 1)
    p = head.params_from_raw(torch.zeros(4, 2), torch.zeros(4, 6), raw)
    assert p.log_std.shape == (4, 2, 3)
    # a scaled sigmoid: -3 + 5 sigmoid(raw), monotone, inside [-3, 2] with a gradient everywhere
    expected = (-3.0 + 5.0 * torch.sigmoid(raw)).reshape(4, 2, 3)
    assert torch.allclose(p.log_std, expected)
    assert (p.log_std.reshape(4, 6)[:, :-1] <= p.log_std.reshape(4, 6)[:, 1:]).all()
    grad_raw = torch.tensor([-6.0, 0.0, 6.0], requires_grad=True)
    squash_log_std(grad_raw, -3.0, 2.0, 1e-3).sum().backward()
    assert (grad_raw.grad > 0).all()  # a mode can always widen or narrow again
    assert unsquash_log_std(0.0, -3.0, 2.0) == pytest.approx(math.log(0.6 / 0.4))
    assert p.log_std.min().item() == pytest.approx(-3.0)
    assert p.log_std.max().item() == pytest.approx(2.0)
    std = p.log_std.exp()
    assert std.min().item() >= 1e-3 and std.min().item() == pytest.approx(math.exp(-3.0))
    # when the floor is above e^log_std_min, the floor binds
    head2 = MDNHead(8, 3, num_modes=2, min_std=0.1, log_std_min=-3.0, log_std_max=2.0)
    p2 = head2.params_from_raw(raw_logits, raw_means, torch.full((4, 6), -1e6))
    assert p2.log_std.exp().min().item() == pytest.approx(0.1, rel=1e-6)
    # a full forward through a head whose log-std layer outputs huge values stays in range
    with torch.no_grad():
        head.log_std.bias.fill_(1e4)
    assert head(torch.randn(7, 8)).log_std.max().item() == pytest.approx(2.0)
    with torch.no_grad():
        head.log_std.bias.fill_(-1e4)
    assert head(torch.randn(7, 8)).log_std.min().item() == pytest.approx(-3.0)


def test_mdn_sample_follows_weights_and_modes():
    b = 4000
    logits = torch.log(torch.tensor([0.25, 0.75])).expand(b, 2)
    means = torch.tensor([[-5.0, 0.0], [5.0, 1.0]]).expand(b, 2, 2)
    log_std = torch.full((b, 2, 2), math.log(0.1))
    params = MDNParams(logits, means, log_std)
    s1 = mdn_sample(params, torch.Generator().manual_seed(0))
    s2 = mdn_sample(params, torch.Generator().manual_seed(0))
    assert torch.equal(s1, s2)  # reproducible with a generator
    assert s1.shape == (b, 2)
    frac_mode1 = (s1[:, 0] > 0).float().mean().item()
    assert frac_mode1 == pytest.approx(0.75, abs=0.03)
    in_mode1 = s1[:, 0] > 0
    assert s1[in_mode1, 0].mean().item() == pytest.approx(5.0, abs=0.02)
    assert s1[in_mode1, 1].std().item() == pytest.approx(0.1, rel=0.1)


def test_mdn_head_fits_bimodal_targets_where_regression_averages():
    torch.manual_seed(0)
    x = torch.ones(256, 4)
    targets = torch.where(torch.arange(256) % 2 == 0, -1.0, 1.0).reshape(256, 1, 1)
    head = MDNHead(4, 1, num_modes=2)
    with torch.no_grad():  # break the symmetry between the two modes
        head.means.bias.copy_(torch.tensor([-0.1, 0.1]))
    opt = torch.optim.Adam(head.parameters(), lr=3e-2)
    for _ in range(300):
        loss = mdn_nll(head(x), targets)
        opt.zero_grad()
        loss.backward()
        opt.step()
    p = head(x[:1])
    means = sorted(p.means[0, :, 0].tolist())
    assert means[0] == pytest.approx(-1.0, abs=0.05) and means[1] == pytest.approx(1.0, abs=0.05)
    w = mixture_weights(p)[0]
    assert w.min().item() > 0.4
    # top-mode mean is one of the two modes, not their average (which regression would give)
    assert abs(top_mode_mean(p).item()) == pytest.approx(1.0, abs=0.05)


# ----------------------------------------------------------------------------- variants
def test_variant_structure():
    full = small_policy("full")
    no_tf = small_policy("no_transformer")
    no_mdn = small_policy("no_mdn")
    n_mha = sum(isinstance(m, nn.MultiheadAttention) for m in full.modules())
    assert n_mha == full.cfg.n_layers == 1
    assert sum(isinstance(m, nn.MultiheadAttention) for m in no_mdn.modules()) == 1
    assert not any(
        isinstance(m, nn.MultiheadAttention | nn.TransformerEncoder) for m in no_tf.modules()
    )
    assert not any("attn" in n or "transformer" in n for n, _ in no_tf.named_parameters())
    # no_mdn: no mixture parameters at all
    assert not any(isinstance(m, MDNHead) for m in no_mdn.modules())
    assert not any("mdn" in n or "logits" in n for n in no_mdn.state_dict())
    assert no_mdn.action_out.out_features == A
    # MDN variants: K logits + K*A means + K*A log-stds
    for pol in (full, no_tf):
        assert pol.mdn.logits.out_features == 2
        assert pol.mdn.means.out_features == pol.mdn.log_std.out_features == 2 * A
    # default-size models are the sizes of the spec
    big = StudentPolicy(StudentCfg(), 93, 5, 3, (24, 32), 29)
    convs = [m for m in big.cnn if isinstance(m, nn.Conv2d)]
    assert [c.out_channels for c in convs] == [24, 32, 48, 64]
    assert [c.kernel_size[0] for c in convs] == [5, 3, 3, 3]
    assert big.fmap_hw == (6, 8) and big.num_tokens == 2 + 5 + 48
    layer = big.transformer.layers[0]
    assert layer.self_attn.embed_dim == 256 and layer.self_attn.num_heads == 8
    assert len(big.transformer.layers) == 2
    w0, w1 = (lay.self_attn.in_proj_weight for lay in big.transformer.layers)
    assert (w0 - w1).abs().max().item() > 1e-2  # layers are initialised independently
    assert isinstance(big.head_mlp[1], nn.ELU)


def test_a_variant_is_its_parts():
    """A variant is built from the parts its YAML names, not from its name: a blind student
    (image: none) has no CNN and no image tokens, and its actions ignore the depth image."""
    blind = small_policy("x_blind", image="none", fusion="transformer", head="mdn")
    assert blind.cnn is None and blind.num_image_tokens == 0
    assert blind.num_tokens == 2 + HIST
    assert not any(isinstance(m, nn.Conv2d) for m in blind.modules())
    x = inputs(8)
    far = (x[0], x[1], torch.ones_like(x[2]))
    torch.testing.assert_close(blind.act_inference(*x), blind.act_inference(*far), rtol=0, atol=0)
    full = small_policy("full")
    assert (full.act_inference(*x) - full.act_inference(*far)).abs().max() > 1e-4
    mlp = small_policy("y", image="none", fusion="mlp", head="deterministic")
    assert mlp.fusion[0].in_features == HIST * P + CMD and not mlp.is_mdn
    # a new name without parts is refused in one line naming the file to fix
    with pytest.raises(ConfigError, match=r"set student.image .* conf/student/z.yaml"):
        StudentCfg(variant="z")
    with pytest.raises(
        ConfigError,
        match="student.fusion='attention' is not a registered fusion part; choose one of transformer, mlp, gru",
    ):
        StudentCfg(variant="full", fusion="attention")


@pytest.mark.parametrize("variant", STUDENTS)
def test_output_shapes_and_loss(variant):
    pol = small_policy(variant)
    x = inputs(6)
    out = pol(*x)
    if not pol.is_mdn:
        assert isinstance(out, torch.Tensor) and out.shape == (6, A)
    else:
        assert isinstance(out, MDNParams)
        assert out.logits.shape == (6, 2)
        assert out.means.shape == out.log_std.shape == (6, 2, A)
    act = pol.act_inference(*x)
    assert act.shape == (6, A) and torch.isfinite(act).all()
    tm, ts = torch.randn(6, A), 0.5 * torch.ones(6, A)
    loss, info = pol.distill_loss(*x, tm, ts, generator=torch.Generator().manual_seed(0))
    assert loss.ndim == 0 and torch.isfinite(loss)
    assert info["loss"] == pytest.approx(loss.item())
    assert info["action_error"] == pytest.approx((act - tm).abs().mean().item(), rel=1e-5)
    if not pol.is_mdn:
        ref = torch.nn.functional.huber_loss(act, tm, delta=1.0)
        assert loss.item() == pytest.approx(ref.item(), rel=1e-6)
    else:
        assert info["mode_weight_0"] + info["mode_weight_1"] == pytest.approx(1.0, abs=1e-6)
        # same generator -> same teacher samples -> same NLL
        loss2, _ = pol.distill_loss(*x, tm, ts, generator=torch.Generator().manual_seed(0))
        assert loss2.item() == pytest.approx(loss.item(), rel=1e-6)
    loss.backward()
    grads = [p.grad for p in pol.parameters() if p.requires_grad]
    assert all(g is not None for g in grads)
    with pytest.raises(ValueError):
        pol(x[0][:, :3], x[1], x[2])


def test_distill_nll_falls_on_fixed_batch():
    pol = small_policy("full")
    x = inputs(32, seed=7)
    g = torch.Generator().manual_seed(11)
    teacher_mean = torch.tanh(x[0][:, -1, :A] + x[1][:, :1])  # a function of the inputs
    teacher_std = torch.full((32, A), 0.3)
    opt = torch.optim.Adam(pol.parameters(), lr=2e-3)
    losses, errs = [], []
    for _ in range(50):
        loss, info = pol.distill_loss(*x, teacher_mean, teacher_std, generator=g)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(info["nll"])
        errs.append(info["action_error"])
    # start: std 1 per dim, NLL ~ A * (0.92 + 0.5 E[err^2]) > 3.5; target samples have
    # std 0.03 (< e^-3 clamp) so the optimum is ~ A * (0.92 - 3) < -7
    assert losses[0] > 3.5
    assert np.mean(losses[-5:]) < 0.5 * losses[0] - 2.0
    assert np.mean(errs[-5:]) < 0.5 * errs[0]


def test_no_mdn_huber_falls_on_fixed_batch():
    pol = small_policy("no_mdn")
    x = inputs(32, seed=7)
    teacher_mean = torch.tanh(x[0][:, -1, :A] + x[1][:, :1])
    opt = torch.optim.Adam(pol.parameters(), lr=2e-3)
    losses = []
    for _ in range(50):
        loss, _ = pol.distill_loss(*x, teacher_mean, torch.ones(32, A))
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.2 * losses[0]


def test_observation_normalization_in_state_dict_and_updates():
    pol = small_policy("full")
    keys = pol.state_dict().keys()
    assert {
        "proprio_normalizer._mean",
        "proprio_normalizer._std",
        "command_normalizer._mean",
        "command_normalizer._std",
    } <= set(keys)
    g = torch.Generator().manual_seed(0)
    hist = 5.0 + 2.0 * torch.randn(512, HIST, P, generator=g)
    cmd = -1.0 + 0.5 * torch.randn(512, CMD, generator=g)
    pol.eval()
    pol.update_normalization(hist, cmd)  # eval mode: no-op
    assert pol.proprio_normalizer.count.item() == 0
    pol.train()
    pol.update_normalization(hist, cmd)
    assert pol.proprio_normalizer.count.item() == 512 * HIST
    assert pol.proprio_normalizer.mean.mean().item() == pytest.approx(5.0, abs=0.05)
    assert pol.proprio_normalizer.std.mean().item() == pytest.approx(2.0, abs=0.05)
    assert pol.command_normalizer.mean.mean().item() == pytest.approx(-1.0, abs=0.05)
    normed = pol.proprio_normalizer(hist)
    assert normed.mean().item() == pytest.approx(0.0, abs=0.01)
    assert normed.std().item() == pytest.approx(1.0, abs=0.02)
    # a fresh policy loaded from the state_dict reproduces the outputs (stats included)
    pol.eval()
    clone = small_policy("full", seed=123).eval()
    x = inputs(4)
    assert not torch.allclose(clone.act_inference(*x), pol.act_inference(*x))
    clone.load_state_dict(pol.state_dict())
    torch.testing.assert_close(clone.act_inference(*x), pol.act_inference(*x), rtol=0, atol=0)


# ----------------------------------------------------------------------------- ONNX
@pytest.mark.parametrize("variant", STUDENTS)
def test_onnx_matches_torch(variant, tmp_path):
    from march.export.onnx_graph import export_student_onnx, read_onnx_metadata

    pol = small_policy(variant)
    pol.train()
    pol.update_normalization(3.0 + torch.randn(64, HIST, P), torch.randn(64, CMD))
    if pol.is_mdn:  # spread the logits so rows pick different top modes
        with torch.no_grad():
            pol.mdn.logits.weight.normal_(0.0, 3.0)
            diff = pol.mdn(pol.features(*inputs(64, seed=2))).logits.diff(dim=-1)
            pol.mdn.logits.bias[1] -= diff.median()
    pol.eval()
    meta = {"obs_layout": "proprio: ang_vel(3) gravity(3) ...", "action_layout": "joint order ..."}
    res = export_student_onnx(pol, tmp_path / f"{variant}.onnx", meta, latency_calls=30)
    assert torch.backends.mha.get_fastpath_enabled()  # global flag restored
    assert res["max_abs_diff"] < 1e-4
    assert 0.0 < res["latency_ms_median"] <= res["latency_ms_p95"] < 1e3
    md = read_onnx_metadata(res["path"])
    assert md["obs_layout"] == meta["obs_layout"] and md["action_layout"] == meta["action_layout"]
    assert md["student_variant"] == variant
    # independent check with our own session at another batch size
    sess = ort.InferenceSession(res["path"], providers=["CPUExecutionProvider"])
    assert [i.name for i in sess.get_inputs()] == ["proprio_hist", "command", "depth"]
    assert [o.name for o in sess.get_outputs()] == ["actions"]
    x = inputs(40, seed=9)
    got = sess.run(
        ["actions"],
        {n: t.numpy() for n, t in zip(["proprio_hist", "command", "depth"], x, strict=True)},
    )[0]
    with torch.no_grad():
        ref = pol.act_inference(*x).numpy()
        if pol.is_mdn:
            top = mixture_weights(pol(*x)).argmax(-1)
            assert 0 < top.sum().item() < 40  # both modes are the top mode for some rows
    assert got.shape == (40, A)
    assert np.max(np.abs(got - ref)) < 1e-4
    assert pol.training is False and next(pol.parameters()).device.type == "cpu"


def deep_policy(variant: str, n_layers: int) -> StudentPolicy:
    from dataclasses import replace

    torch.manual_seed(0)
    return StudentPolicy(replace(small_cfg(variant), n_layers=n_layers), P, HIST, CMD, HW, A)


@pytest.mark.parametrize("variant", STUDENTS)
@pytest.mark.parametrize("n_layers", [1, 3])
def test_deploy_graph_is_act_inference(variant, n_layers):
    """The export's fast graph (last layer CLS-only, attention written out) computes the same
    actions as the policy, mode choice included, for any depth of encoder."""
    from march.export.onnx_graph import DeployGraph

    pol = deep_policy(variant, n_layers).train()
    pol.update_normalization(1.0 + 2.0 * torch.randn(64, HIST, P), torch.randn(64, CMD))
    pol.eval()
    x = inputs(64, seed=5)
    if pol.is_mdn:  # spread the logits and centre them so rows pick different top modes
        with torch.no_grad():
            pol.mdn.logits.weight.normal_(0.0, 3.0)
            diff = pol.mdn(pol.features(*x)).logits.diff(dim=-1)
            pol.mdn.logits.bias[1] -= diff.median()
    graph = DeployGraph(pol).eval()
    with torch.no_grad():
        want = pol.act_inference(*x)
        got = graph(*x)
        keep = torch.ones(64, dtype=torch.bool)
        if pol.is_mdn:
            logits = pol(*x).logits
            top = logits.argmax(-1)
            assert 0 < top.sum().item() < 64  # both modes are chosen by some rows
            # a near-tie may flip with float rounding (as between torch and onnxruntime)
            keep = (logits[:, 0] - logits[:, 1]).abs() > 1e-3
            assert keep.sum() >= 60
    assert got.shape == want.shape == (64, A)
    torch.testing.assert_close(got[keep], want[keep], rtol=0, atol=2e-5)


def test_deploy_graph_exports_without_shape_arithmetic(tmp_path):
    """The deploy ONNX has no Shape/If/Expand nodes (the traced graph's per-layer shape
    arithmetic); both graphs match the policy."""
    import onnx

    from march.export.onnx_graph import export_student_onnx, read_onnx_metadata

    pol = deep_policy("full", 2).eval()
    ops = {}
    for graph in ("deploy", "trace"):
        res = export_student_onnx(pol, tmp_path / f"{graph}.onnx", {}, graph=graph, latency_calls=5)
        assert res["max_abs_diff"] < 1e-4 and res["graph"] == graph
        ops[graph] = [n.op_type for n in onnx.load(res["path"]).graph.node]
        assert read_onnx_metadata(res["path"])["export_graph"] == graph
    assert not {"Shape", "If", "Expand"} & set(ops["deploy"])
    assert {"Shape"} & set(ops["trace"])
    with pytest.raises(ValueError, match="graph="):
        export_student_onnx(pol, tmp_path / "x.onnx", {}, graph="fast")
