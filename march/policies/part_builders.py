"""The student's parts, each registered under its ``student.<kind>`` value (march.config.parts).

A part is a class with two static methods, registered with :func:`student_part`:

* image: ``build(policy, cfg, block) -> (channels, (h, w))`` and ``forward(policy, depth) ->
  (B, channels, h, w) feature map or None``;
* fusion: ``build(policy, cfg, block, channels, tokens) -> width`` and ``forward(policy, p, c,
  fmap) -> (B, width)`` (``p`` the normalised history (B, H, P), ``c`` the normalised command);
* head: ``mixture`` (True: an MDN, NLL loss; False: one action, Huber loss), ``build(policy,
  cfg, block, width, num_actions)`` and ``forward(policy, z)``.

``build`` puts its modules on the policy (the paper's parts under the attribute names their
checkpoints hold, so those keep loading); ``block`` is the part's own config dataclass
(``student.parts.<name>``) or None. A new part is one class here (or in your module, named in
``extra_modules``) and a YAML; ``tests/test_student.py`` runs every registered variant.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from march.config.parts import register_part
from march.policies.mdn import MDNHead


def student_part(kind: str, name: str, block: type | None = None) -> Callable[[type], type]:
    """Register the decorated class as the ``student.<kind>=<name>`` part (with its config
    dataclass ``block``, set under ``student.parts.<name>``)."""

    def register(cls: type) -> type:
        register_part(kind, name, builder=cls, block=block, doc=(cls.__doc__ or "").strip())
        return cls

    return register


def activation(name: str) -> nn.Module:
    table = {"elu": nn.ELU, "relu": nn.ReLU, "gelu": nn.GELU, "silu": nn.SiLU, "tanh": nn.Tanh}
    if name not in table:
        raise ValueError(f"unknown activation {name!r}; choose from {sorted(table)}")
    return table[name]()


def mlp(in_dim: int, hidden: Sequence[int], act: str) -> tuple[nn.Sequential, int]:
    layers: list[nn.Module] = []
    for h in hidden:
        layers += [nn.Linear(in_dim, h), activation(act)]
        in_dim = h
    return nn.Sequential(*layers), in_dim


# ---------------------------------------------------------------------------- image
@student_part("image", "cnn")
class CnnImage:
    """The depth CNN (student.cnn_channels / cnn_kernels / cnn_strides, same padding)."""

    @staticmethod
    def build(policy: Any, cfg: Any, block: Any) -> tuple[int, tuple[int, int]]:
        convs: list[nn.Module] = []
        in_ch = 1
        for ch, k, s in zip(cfg.cnn_channels, cfg.cnn_kernels, cfg.cnn_strides, strict=True):
            convs += [nn.Conv2d(in_ch, ch, k, stride=s, padding=k // 2), activation(cfg.activation)]
            in_ch = ch
        policy.cnn = nn.Sequential(*convs)
        with torch.no_grad():
            fmap = policy.cnn(torch.zeros(1, 1, *policy.image_hw))
        return int(fmap.shape[1]), (int(fmap.shape[2]), int(fmap.shape[3]))

    @staticmethod
    def forward(policy: Any, depth: torch.Tensor) -> torch.Tensor:
        return policy.cnn(depth)


@student_part("image", "none")
class NoImage:
    """The depth image is an input nobody reads (a blind student)."""

    @staticmethod
    def build(policy: Any, cfg: Any, block: Any) -> tuple[int, tuple[int, int]]:
        policy.cnn = None
        return 0, (0, 0)

    @staticmethod
    def forward(policy: Any, depth: torch.Tensor) -> None:
        return None


# ---------------------------------------------------------------------------- fusion
@student_part("fusion", "mlp")
class MlpFusion:
    """Flattened image features ++ flattened history ++ command -> MLP (student.fusion_mlp)."""

    @staticmethod
    def build(policy: Any, cfg: Any, block: Any, channels: int, tokens: int) -> int:
        fused_in = channels * tokens + policy.history_len * policy.proprio_dim + policy.command_dim
        policy.fusion, width = mlp(fused_in, cfg.fusion_mlp, cfg.activation)
        return width

    @staticmethod
    def forward(policy: Any, p: torch.Tensor, c: torch.Tensor, fmap: Any) -> torch.Tensor:
        parts = [p.flatten(1), c] if fmap is None else [fmap.flatten(1), p.flatten(1), c]
        return policy.fusion(torch.cat(parts, dim=-1))


@student_part("fusion", "transformer")
class TransformerFusion:
    """[CLS, command, history, image tokens] + learned positions -> pre-LN transformer; the CLS
    output, layer-normed (student.d_model, n_heads, n_layers, dim_feedforward)."""

    @staticmethod
    def build(policy: Any, cfg: Any, block: Any, channels: int, tokens: int) -> int:
        d = cfg.d_model
        policy.image_proj = nn.Linear(channels, d) if channels else None
        policy.proprio_proj = nn.Linear(policy.proprio_dim, d)
        policy.command_proj = nn.Linear(policy.command_dim, d)
        policy.cls_token = nn.Parameter(torch.zeros(1, 1, d))
        # token order: [CLS, command, history_1..history_H, image_1..image_N]
        policy.num_tokens = 2 + policy.history_len + tokens
        policy.pos_embed = nn.Parameter(torch.zeros(1, policy.num_tokens, d))
        nn.init.normal_(policy.cls_token, std=0.02)
        nn.init.normal_(policy.pos_embed, std=0.02)

        def make_layer() -> nn.TransformerEncoderLayer:
            return nn.TransformerEncoderLayer(
                d_model=d,
                nhead=cfg.n_heads,
                dim_feedforward=cfg.dim_feedforward,
                dropout=0.0,
                activation="gelu",
                batch_first=True,
                norm_first=True,
            )

        policy.transformer = nn.TransformerEncoder(
            make_layer(), num_layers=cfg.n_layers, enable_nested_tensor=False
        )
        # TransformerEncoder deep-copies one layer, so every layer would start with the same
        # weights; give each layer its own initialisation instead.
        policy.transformer.layers = nn.ModuleList(make_layer() for _ in range(cfg.n_layers))
        policy.out_norm = nn.LayerNorm(d)
        return d

    @staticmethod
    def forward(policy: Any, p: torch.Tensor, c: torch.Tensor, fmap: Any) -> torch.Tensor:
        hist = policy.proprio_proj(p)  # (B, H, d)
        cmd = policy.command_proj(c).unsqueeze(1)  # (B, 1, d)
        cls = policy.cls_token.expand(hist.shape[0], -1, -1)
        seq = [cls, cmd, hist]
        if fmap is not None:
            seq.append(policy.image_proj(fmap.flatten(2).transpose(1, 2)))  # (B, N, d)
        tokens = torch.cat(seq, dim=1) + policy.pos_embed
        return policy.out_norm(policy.transformer(tokens)[:, 0])


@dataclass
class GruBlock:
    """``student.parts.gru``: the GRU fusion's own sizes."""

    hidden_size: int = 128
    """GRU state width (the fused feature's width)."""
    num_layers: int = 1
    """Stacked GRU layers."""

    def __post_init__(self) -> None:
        for key in ("hidden_size", "num_layers"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{key}={value!r} must be an integer >= 1")


@student_part("fusion", "gru", block=GruBlock)
class GruFusion:
    """A GRU over the history (oldest first), its last state ++ command ++ flattened image
    features -> linear -> activation (student.parts.gru: hidden_size, num_layers)."""

    @staticmethod
    def build(policy: Any, cfg: Any, block: GruBlock, channels: int, tokens: int) -> int:
        h = block.hidden_size
        policy.gru = nn.GRU(policy.proprio_dim, h, num_layers=block.num_layers, batch_first=True)
        policy.gru_out = nn.Sequential(
            nn.Linear(h + policy.command_dim + channels * tokens, h), activation(cfg.activation)
        )
        return h

    @staticmethod
    def forward(policy: Any, p: torch.Tensor, c: torch.Tensor, fmap: Any) -> torch.Tensor:
        out, _ = policy.gru(p)  # (B, H, h)
        parts = [out[:, -1], c] if fmap is None else [out[:, -1], c, fmap.flatten(1)]
        return policy.gru_out(torch.cat(parts, dim=-1))


# ---------------------------------------------------------------------------- head
@student_part("head", "mdn")
class MdnHead:
    """Mixture density network (student.num_modes, min_std, log_std_*): NLL of teacher
    samples; acts with the top mode's mean."""

    mixture = True

    @staticmethod
    def build(policy: Any, cfg: Any, block: Any, width: int, num_actions: int) -> None:
        policy.mdn = MDNHead(
            width,
            num_actions,
            num_modes=cfg.num_modes,
            min_std=cfg.min_std,
            log_std_min=cfg.log_std_min,
            log_std_max=cfg.log_std_max,
            init_log_std=cfg.init_log_std,
        )

    @staticmethod
    def forward(policy: Any, z: torch.Tensor) -> Any:
        return policy.mdn(z)


@student_part("head", "deterministic")
class DeterministicHead:
    """One action, Huber against the teacher mean (student.huber_delta)."""

    mixture = False

    @staticmethod
    def build(policy: Any, cfg: Any, block: Any, width: int, num_actions: int) -> None:
        policy.action_out = nn.Linear(width, num_actions)

    @staticmethod
    def forward(policy: Any, z: torch.Tensor) -> torch.Tensor:
        return policy.action_out(z)
