"""Student parts from a registry (issue 36, item 5): each ``image`` / ``fusion`` / ``head``
value maps to its builder and its own config block; an unknown value is one line naming the
known ones (never a silent transformer); a part of your own is one class; the paper variants'
parameters keep their checkpoint names."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch

from march.config import ConfigError, StudentCfg
from march.config.cli import load
from march.config.parts import PARTS
from march.policies.part_builders import student_part
from march.policies.student import StudentPolicy

ROOT = Path(__file__).resolve().parent.parent
P, HIST, CMD, HW, A = 7, 3, 3, (8, 8), 4
SMALL = dict(cnn_channels=(4,), cnn_kernels=(3,), cnn_strides=(2,), head_hidden=(16,))


def test_unknown_part_is_one_line_naming_the_known_ones():
    with pytest.raises(ConfigError) as err:
        load(["compute=smoke", "student.fusion=gruu"])
    msg = str(err.value)
    assert msg.startswith("student.fusion='gruu' is not a registered fusion part; choose one of")
    assert all(n in msg for n in ("transformer", "mlp", "gru")) and "\n" not in msg
    for kind, bad in (("image", "rgb"), ("head", "gmm")):
        with pytest.raises(ConfigError, match=f"student.{kind}='{bad}' is not a registered"):
            StudentCfg(
                variant="x", **{**{"image": "cnn", "fusion": "mlp", "head": "mdn"}, kind: bad}
            )


def test_cli_refuses_an_unknown_fusion_in_one_line():
    res = subprocess.run(
        [sys.executable, "-m", "march.inspect", "compute=smoke", "student.fusion=gruu"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.returncode == 2 and len(lines) == 1, res.stderr[-2000:]
    assert "student.fusion='gruu' is not a registered fusion part" in lines[0]


def test_gru_has_its_own_block():
    cfg = load(["compute=smoke", "student=gru", "student.parts.gru.hidden_size=24"])
    assert (cfg.student.fusion, cfg.student.parts["gru"]["hidden_size"]) == ("gru", 24)
    pol = StudentPolicy(StudentCfg(**{**vars(cfg.student), **SMALL}), P, HIST, CMD, HW, A)
    assert pol.gru.hidden_size == 24 and pol.gru.num_layers == 1
    assert not hasattr(pol, "transformer")  # nothing silently built beside it
    # d_model does not touch it: the part's sizes are its own
    other = StudentPolicy(
        StudentCfg(**{**vars(cfg.student), **SMALL, "d_model": 8, "n_heads": 2}),
        P,
        HIST,
        CMD,
        HW,
        A,
    )
    assert other.num_params() == pol.num_params()
    with pytest.raises(ConfigError, match=r"student.parts.gru: unknown key\(s\) \['hiden'\]"):
        load(["compute=smoke", "student=gru", "+student.parts.gru.hiden=3"])
    with pytest.raises(ConfigError, match="hidden_size=0 must be an integer >= 1"):
        load(["compute=smoke", "student=gru", "student.parts.gru.hidden_size=0"])
    with pytest.raises(ConfigError, match="has no block of its own"):
        load(["compute=smoke", "+student.parts.transformer={d: 3}"])


def test_gru_forward_reads_history_order():
    """The GRU's state depends on the order of the history (a transformer with positions and
    the GRU do; an order-blind pooling would not): swapping two history steps moves the action."""
    cfg = StudentCfg(variant="gru", image="none", fusion="gru", head="deterministic", **SMALL)
    torch.manual_seed(0)
    pol = StudentPolicy(cfg, P, HIST, CMD, HW, A).eval()
    x = torch.randn(5, HIST, P), torch.randn(5, CMD), torch.rand(5, 1, *HW)
    out = pol.act_inference(*x)
    assert out.shape == (5, A) and torch.isfinite(out).all()
    swapped = x[0][:, [1, 0, 2]]
    assert not torch.allclose(pol.act_inference(swapped, *x[1:]), out)


@dataclass
class MeanBlock:
    width: int = 6


def test_a_part_of_your_own_is_one_class():
    @student_part("fusion", "mean_pool", block=MeanBlock)
    class MeanPool:
        """Mean of the history ++ command -> linear."""

        @staticmethod
        def build(policy, cfg, block, channels, tokens):
            policy.pool_out = torch.nn.Linear(policy.proprio_dim + policy.command_dim, block.width)
            return block.width

        @staticmethod
        def forward(policy, p, c, fmap):
            return policy.pool_out(torch.cat([p.mean(1), c], -1))

    assert PARTS["fusion"]["mean_pool"].builder is MeanPool
    cfg = StudentCfg(
        variant="pool",
        image="none",
        fusion="mean_pool",
        head="mdn",
        parts={"mean_pool": {"width": 5}},
        **SMALL,
    )
    pol = StudentPolicy(cfg, P, HIST, CMD, HW, A)
    assert pol.pool_out.out_features == 5 and pol.head_mlp[0].in_features == 5
    assert pol.act_inference(
        torch.randn(2, HIST, P), torch.randn(2, CMD), torch.rand(2, 1, *HW)
    ).shape == (2, A)


def test_paper_variants_keep_their_checkpoint_names():
    """A checkpoint of the paper's variants stores these top-level names (written before the
    registry); the registry's builders put the modules back under them."""
    want = {
        "full": {
            "proprio_normalizer",
            "command_normalizer",
            "cnn",
            "image_proj",
            "proprio_proj",
            "command_proj",
            "cls_token",
            "pos_embed",
            "transformer",
            "out_norm",
            "head_mlp",
            "mdn",
        },
        "no_transformer": {
            "proprio_normalizer",
            "command_normalizer",
            "cnn",
            "fusion",
            "head_mlp",
            "mdn",
        },
        "no_mdn": {
            "proprio_normalizer",
            "command_normalizer",
            "cnn",
            "image_proj",
            "proprio_proj",
            "command_proj",
            "cls_token",
            "pos_embed",
            "transformer",
            "out_norm",
            "head_mlp",
            "action_out",
        },
    }
    for variant, names in want.items():
        pol = StudentPolicy(StudentCfg(variant=variant, **SMALL), P, HIST, CMD, HW, A)
        assert {k.split(".")[0] for k in pol.state_dict()} == names, variant
