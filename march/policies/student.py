"""Vision + proprioception student policy (CNN -> transformer -> MDN) and its two ablations.

Inputs (one control step, batch B):

* ``proprio_hist`` (B, history_len, proprio_dim): the last ``history_len`` proprioception vectors,
  oldest first (the order only has to be the same in training and deployment);
* ``command`` (B, command_dim): the velocity command (v_x m/s, v_y m/s, yaw rate rad/s);
* ``depth`` (B, 1, H, W): one depth image normalised to [0, 1] over the camera range (1 = far or no return; H=24 rows, W=32 columns).

Proprioception and command pass through empirical running mean/std normalisers (rsl-rl's
``EmpiricalNormalization``; buffers live in the state_dict and are baked into the ONNX export).
One normaliser of size ``proprio_dim`` is shared by all history steps.

Variants (``StudentCfg.variant``, one per ``conf/student/<name>.yaml``) are data: each names
its parts, ``image``, ``fusion`` and ``head``, each value a registered part
(:mod:`march.config.parts`; builders in :mod:`march.policies.part_builders`; ``python -m
march.inspect list`` shows them), and this module builds whatever combination is asked for.
The paper's three:

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

from typing import Any

import torch
import torch.nn.functional as F
from rsl_rl.modules.normalization import EmpiricalNormalization
from torch import nn

from march.config import StudentCfg
from march.config.parts import PARTS, block, check_value
from march.policies.mdn import (
    MDNParams,
    mdn_nll,
    mixture_weights,
    mode_weight_entropy,
    top_mode_mean,
)
from march.policies.part_builders import mlp as _mlp


def _part(kind: str, name: str) -> object:
    check_value(kind, name)
    builder = PARTS[kind][name].builder
    if builder is None:
        raise ValueError(f"student.{kind}={name} is registered without a builder")
    return builder


class StudentPolicy(nn.Module):
    """Depth-image + proprioception student; see the module docstring for the three variants."""

    @classmethod
    def from_layout(cls, cfg: StudentCfg, layout: dict[str, Any]) -> StudentPolicy:
        """The student a checkpoint's ``layout`` describes (its sizes), on torch's default device
        (the gate builds it under ``torch.device("meta")``: no weights allocated)."""
        return cls(
            cfg,
            proprio_dim=layout["proprio_dim"],
            history_len=layout["history_len"],
            command_dim=3,
            image_hw=tuple(layout["image_hw"]),
            num_actions=layout["num_actions"],
        )

    def __init__(
        self,
        cfg: StudentCfg,
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

        # Each part from its registry entry (march.policies.part_builders), in this order (the
        # order the paper variants' parameters were always created in: same seed, same init).
        self._image = _part("image", self.image)
        self._fusion = _part("fusion", self.fusion_kind)
        self._head = _part("head", cfg.head)
        blocks = {k: block(cfg.parts, k, v) for k, v in self.part_names().items()}
        self.cnn_out_channels, self.fmap_hw = self._image.build(self, cfg, blocks["image"])
        self.num_image_tokens = self.fmap_hw[0] * self.fmap_hw[1]
        trunk_dim = self._fusion.build(
            self, cfg, blocks["fusion"], self.cnn_out_channels, self.num_image_tokens
        )
        self.is_mdn = bool(self._head.mixture)
        self.head_mlp, head_dim = _mlp(trunk_dim, cfg.head_hidden, cfg.activation)
        self._head.build(self, cfg, blocks["head"], head_dim, num_actions)

    def part_names(self) -> dict[str, str]:
        return {"image": self.image, "fusion": self.fusion_kind, "head": self.cfg.head}

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
        fmap = self._image.forward(self, depth)  # (B, Ch, h, w) or None
        z = self._fusion.forward(self, p, c, fmap)
        return self.head_mlp(z)

    def forward(
        self, proprio_hist: torch.Tensor, command: torch.Tensor, depth: torch.Tensor
    ) -> MDNParams | torch.Tensor:
        """MDN head: :class:`MDNParams`; deterministic head: (B, A) actions."""
        return self._head.forward(self, self.features(proprio_hist, command, depth))

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
