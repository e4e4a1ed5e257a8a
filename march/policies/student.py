"""Vision + proprioception student policy (CNN -> transformer -> MDN) and its two ablations.

Inputs (one control step, batch B):

* ``proprio_hist`` (B, history_len, proprio_dim): the last ``history_len`` proprioception vectors,
  oldest first (the order only has to be the same in training and deployment);
* ``command`` (B, command_dim): the velocity command (v_x m/s, v_y m/s, yaw rate rad/s);
* ``depth`` (B, 1, H, W): one depth image normalised to [0, 1] over the camera range (1 = far or no return; H=24 rows, W=32 columns).

Proprioception and command pass through empirical running mean/std normalisers (rsl-rl's
``EmpiricalNormalization``; buffers live in the state_dict and are baked into the ONNX export).
One normaliser of size ``proprio_dim`` is shared by all history steps.

Variants (``StudentNetCfg.variant``, one per ``conf/student/<name>.yaml``) are data: each names
its parts, ``image`` (cnn | none), ``fusion`` (transformer | mlp) and ``head`` (mdn |
deterministic), and this module builds whatever combination is asked for. The paper's three:

* ``full``: CNN feature map -> one token per spatial cell (linear to d_model) + one token per
  history step + a command token + a learned CLS token, learned positional embedding over the whole
  sequence, pre-LN ``nn.TransformerEncoder``; the CLS output (LayerNorm) feeds an MLP and the MDN.
* ``no_transformer``: flattened CNN features ++ flattened normalised history ++ command -> MLP
  ``fusion_mlp`` -> the same MLP + MDN head. No attention anywhere.
* ``no_mdn``: the ``full`` trunk with a deterministic MLP head (no mixture), trained with a Huber
  loss against the teacher's mean action.

With ``image: none`` the depth image is still an input (every variant takes the same inputs) but
nothing reads it: no CNN, no image tokens.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from rsl_rl.modules.normalization import EmpiricalNormalization
from torch import nn

from march.config import STUDENTS, StudentCfg
from march.policies.mdn import (
    MDNHead,
    MDNParams,
    mdn_nll,
    mixture_weights,
    mode_weight_entropy,
    top_mode_mean,
)

VARIANTS: tuple[str, ...] = STUDENTS
"""The registered student variants (``conf/student/``; march.config.registry)."""


StudentNetCfg = StudentCfg
"""The architecture is the ``student`` section of the run config (march.config.StudentCfg)."""


def _activation(name: str) -> nn.Module:
    table = {"elu": nn.ELU, "relu": nn.ReLU, "gelu": nn.GELU, "silu": nn.SiLU, "tanh": nn.Tanh}
    if name not in table:
        raise ValueError(f"unknown activation {name!r}; choose from {sorted(table)}")
    return table[name]()


def _mlp(in_dim: int, hidden: Sequence[int], activation: str) -> tuple[nn.Sequential, int]:
    layers: list[nn.Module] = []
    for h in hidden:
        layers += [nn.Linear(in_dim, h), _activation(activation)]
        in_dim = h
    return nn.Sequential(*layers), in_dim


class StudentPolicy(nn.Module):
    """Depth-image + proprioception student; see the module docstring for the three variants."""

    def __init__(
        self,
        cfg: StudentNetCfg,
        proprio_dim: int,
        history_len: int,
        command_dim: int,
        image_hw: tuple[int, int],
        num_actions: int,
    ) -> None:
        super().__init__()
        if not len(cfg.cnn_channels) == len(cfg.cnn_kernels) == len(cfg.cnn_strides):
            raise ValueError("cnn_channels, cnn_kernels and cnn_strides need the same length")
        self.cfg = cfg
        self.variant: str = cfg.variant
        self.image: str = cfg.image
        self.fusion_kind: str = cfg.fusion
        self.is_mdn: bool = cfg.head == "mdn"
        self.proprio_dim = proprio_dim
        self.history_len = history_len
        self.command_dim = command_dim
        self.image_hw = (int(image_hw[0]), int(image_hw[1]))
        self.num_actions = num_actions

        self.proprio_normalizer = EmpiricalNormalization(proprio_dim, eps=cfg.normalizer_eps)
        self.command_normalizer = EmpiricalNormalization(command_dim, eps=cfg.normalizer_eps)

        if self.image == "cnn":
            convs: list[nn.Module] = []
            in_ch = 1
            for ch, k, s in zip(cfg.cnn_channels, cfg.cnn_kernels, cfg.cnn_strides, strict=True):
                convs += [
                    nn.Conv2d(in_ch, ch, k, stride=s, padding=k // 2),
                    _activation(cfg.activation),
                ]
                in_ch = ch
            self.cnn = nn.Sequential(*convs)
            with torch.no_grad():
                fmap = self.cnn(torch.zeros(1, 1, *self.image_hw))
            self.cnn_out_channels = int(fmap.shape[1])
            self.fmap_hw = (int(fmap.shape[2]), int(fmap.shape[3]))
        else:  # image: none
            self.cnn = None
            self.cnn_out_channels = 0
            self.fmap_hw = (0, 0)
        self.num_image_tokens = self.fmap_hw[0] * self.fmap_hw[1]

        if self.fusion_kind == "mlp":
            fused_in = (
                self.cnn_out_channels * self.num_image_tokens
                + history_len * proprio_dim
                + command_dim
            )
            self.fusion, trunk_dim = _mlp(fused_in, cfg.fusion_mlp, cfg.activation)
        else:
            d = cfg.d_model
            self.image_proj = nn.Linear(self.cnn_out_channels, d) if self.cnn is not None else None
            self.proprio_proj = nn.Linear(proprio_dim, d)
            self.command_proj = nn.Linear(command_dim, d)
            self.cls_token = nn.Parameter(torch.zeros(1, 1, d))
            # token order: [CLS, command, history_1..history_H, image_1..image_N]
            self.num_tokens = 2 + history_len + self.num_image_tokens
            self.pos_embed = nn.Parameter(torch.zeros(1, self.num_tokens, d))
            nn.init.normal_(self.cls_token, std=0.02)
            nn.init.normal_(self.pos_embed, std=0.02)

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

            self.transformer = nn.TransformerEncoder(
                make_layer(), num_layers=cfg.n_layers, enable_nested_tensor=False
            )
            # TransformerEncoder deep-copies one layer, so every layer would start with the same
            # weights; give each layer its own initialisation instead.
            self.transformer.layers = nn.ModuleList(make_layer() for _ in range(cfg.n_layers))
            self.out_norm = nn.LayerNorm(d)
            trunk_dim = d

        self.head_mlp, head_dim = _mlp(trunk_dim, cfg.head_hidden, cfg.activation)
        if self.is_mdn:
            self.mdn = MDNHead(
                head_dim,
                num_actions,
                num_modes=cfg.num_modes,
                min_std=cfg.min_std,
                log_std_min=cfg.log_std_min,
                log_std_max=cfg.log_std_max,
                init_log_std=cfg.init_log_std,
            )
        else:
            self.action_out = nn.Linear(head_dim, num_actions)

    # ------------------------------------------------------------------ forward
    def _check_inputs(
        self, proprio_hist: torch.Tensor, command: torch.Tensor, depth: torch.Tensor
    ) -> None:
        if proprio_hist.shape[1:] != (self.history_len, self.proprio_dim):
            raise ValueError(
                f"proprio_hist must be (B, {self.history_len}, {self.proprio_dim}), "
                f"got {tuple(proprio_hist.shape)}"
            )
        if command.shape[1:] != (self.command_dim,):
            raise ValueError(f"command must be (B, {self.command_dim}), got {tuple(command.shape)}")
        if depth.shape[1:] != (1, *self.image_hw):
            raise ValueError(f"depth must be (B, 1, {self.image_hw}), got {tuple(depth.shape)}")

    def features(
        self, proprio_hist: torch.Tensor, command: torch.Tensor, depth: torch.Tensor
    ) -> torch.Tensor:
        """(B, head_hidden[-1]) fused feature fed to the output layer."""
        if not torch.jit.is_tracing() and not torch.compiler.is_compiling():
            self._check_inputs(proprio_hist, command, depth)
        p = self.proprio_normalizer(proprio_hist)  # (B, H, P); stats broadcast over H
        c = self.command_normalizer(command)  # (B, C)
        fmap = self.cnn(depth) if self.cnn is not None else None  # (B, Ch, h, w)
        if self.fusion_kind == "mlp":
            parts = [p.flatten(1), c] if fmap is None else [fmap.flatten(1), p.flatten(1), c]
            z = self.fusion(torch.cat(parts, dim=-1))
        else:
            hist = self.proprio_proj(p)  # (B, H, d)
            cmd = self.command_proj(c).unsqueeze(1)  # (B, 1, d)
            cls = self.cls_token.expand(hist.shape[0], -1, -1)
            seq = [cls, cmd, hist]
            if fmap is not None:
                seq.append(self.image_proj(fmap.flatten(2).transpose(1, 2)))  # (B, N, d)
            tokens = torch.cat(seq, dim=1) + self.pos_embed
            z = self.out_norm(self.transformer(tokens)[:, 0])
        return self.head_mlp(z)

    def forward(
        self, proprio_hist: torch.Tensor, command: torch.Tensor, depth: torch.Tensor
    ) -> MDNParams | torch.Tensor:
        """MDN head: :class:`MDNParams`; deterministic head: (B, A) actions."""
        z = self.features(proprio_hist, command, depth)
        if self.is_mdn:
            return self.mdn(z)
        return self.action_out(z)

    def act_inference(
        self, proprio_hist: torch.Tensor, command: torch.Tensor, depth: torch.Tensor
    ) -> torch.Tensor:
        """(B, A) deterministic action: top-mode mean (MDN) or the regression output (no_mdn)."""
        out = self.forward(proprio_hist, command, depth)
        if self.is_mdn:
            return top_mode_mean(out)
        return out

    # ------------------------------------------------------------------ training
    @torch.no_grad()
    def update_normalization(self, proprio_hist: torch.Tensor, command: torch.Tensor) -> None:
        """Update the running mean/std of proprioception and command (no-op in eval mode)."""
        self.proprio_normalizer.update(proprio_hist.reshape(-1, self.proprio_dim))
        self.command_normalizer.update(command.reshape(-1, self.command_dim))

    def distill_loss(
        self,
        proprio_hist: torch.Tensor,
        command: torch.Tensor,
        depth: torch.Tensor,
        teacher_mean: torch.Tensor,
        teacher_std: torch.Tensor,
        num_samples: int = 8,
        std_scale: float = 0.1,
        generator: torch.Generator | None = None,
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """Distillation loss and logging info.

        MDN variants: mean NLL of ``num_samples`` actions per row drawn from
        N(teacher_mean, (std_scale * teacher_std)^2) (paper eq. distillation loss; 8 samples,
        scale 0.1). ``no_mdn``: Huber(delta=cfg.huber_delta) against ``teacher_mean``.
        ``generator`` (optional, for reproducible teacher samples) must live on the device of
        ``teacher_mean``.

        info: ``loss``, ``action_error`` (mean |act_inference - teacher_mean|), and for the MDN
        ``nll``, ``mode_weight_k`` (batch-mean weight of mode k), ``top_mode_weight`` (batch-mean
        weight of the chosen mode), ``mode_entropy`` (nats), ``mean_std`` (mean std of all modes).
        """
        out = self.forward(proprio_hist, command, depth)
        info: dict[str, float] = {}
        if self.is_mdn:
            noise = torch.randn(
                (teacher_mean.shape[0], num_samples, teacher_mean.shape[-1]),
                generator=generator,
                device=teacher_mean.device,
                dtype=teacher_mean.dtype,
            )
            targets = teacher_mean.unsqueeze(1) + std_scale * teacher_std.unsqueeze(1) * noise
            loss = mdn_nll(out, targets.detach())
            with torch.no_grad():
                action = top_mode_mean(out)
                w = mixture_weights(out)
                info["nll"] = float(loss.detach())
                for k in range(w.shape[-1]):
                    info[f"mode_weight_{k}"] = float(w[:, k].mean())
                info["top_mode_weight"] = float(w.max(dim=-1).values.mean())
                info["mode_entropy"] = float(mode_weight_entropy(out).mean())
                info["mean_std"] = float(out.log_std.exp().mean())
        else:
            action = out
            loss = F.huber_loss(out, teacher_mean.detach(), delta=self.cfg.huber_delta)
            info["huber"] = float(loss.detach())
        info["loss"] = float(loss.detach())
        info["action_error"] = float((action.detach() - teacher_mean).abs().mean())
        return loss, info

    def num_params(self, trainable_only: bool = True) -> int:
        """Number of (trainable) parameters; normaliser buffers are not parameters."""
        return sum(p.numel() for p in self.parameters() if p.requires_grad or not trainable_only)
