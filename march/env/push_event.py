"""The paper's random push without a host sync per step.

mjlab's ``interval`` events pick the envs whose timer ran out with
``(time_left < 1e-6).nonzero()`` and ``len(...)`` every step: one host sync per step on a
GPU. :class:`interval_push` is a class-based ``step`` event (mjlab calls it every step, at the
place where it applies the interval events, just before them) that keeps the same per-env timer
and pushes with masks:

- each env's timer starts at U(lower, upper) s, is drawn again on each of its episode resets
  and counts down by the env's step time; when it is below 1e-6 s the env is pushed and its
  timer is drawn again from U(lower, upper): mjlab's rule;
- a push adds a uniform offset in ``velocity_range`` (x, y, z, roll, pitch, yaw; world frame)
  to the root link velocity: ``push_by_setting_velocity``'s arithmetic, row for row;
- the envs that are not pushed keep their root velocity bit for bit (their ``qvel`` row is
  written back unchanged, not recomputed).

The distributions are mjlab's; the random stream is not (every env draws a timer and an offset
every step, the pushed ones keep theirs), so a seeded run pushes at other times than it would
with mjlab's term.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import torch
from mjlab.utils.lab_api.math import quat_apply_inverse

if TYPE_CHECKING:
    from mjlab.envs import ManagerBasedRlEnv

SE3_KEYS = ("x", "y", "z", "roll", "pitch", "yaw")
"""The offsets' order (mjlab's ``_SE3_KEYS``)."""


class interval_push:  # noqa: N801 - an mjlab term is named like a function
    """A class-based ``step`` event: ``cfg.interval_range_s`` (as an interval event's),
    ``cfg.params`` ``velocity_range`` and ``asset_cfg`` (module docstring)."""

    def __init__(self, cfg: Any, env: ManagerBasedRlEnv) -> None:
        lower, upper = cfg.interval_range_s
        if not 0.0 <= lower <= upper:
            raise ValueError(f"interval_range_s {cfg.interval_range_s}: need 0 <= lower <= upper")
        self.lower, self.upper = float(lower), float(upper)
        self.device = env.device
        self.time_left = self._draw(env.num_envs)
        ranges = [cfg.params["velocity_range"].get(k, (0.0, 0.0)) for k in SE3_KEYS]
        r = torch.tensor(ranges, dtype=torch.float32, device=env.device)
        self.lo, self.span = r[:, 0], r[:, 1] - r[:, 0]

    def _draw(self, n: int) -> torch.Tensor:
        return torch.rand(n, device=self.device) * (self.upper - self.lower) + self.lower

    def reset(self, env_ids: torch.Tensor | None = None) -> None:
        """A new timer for each reset env (mjlab's interval timers on ``event_manager.reset``)."""
        if env_ids is None:
            self.time_left = self._draw(self.time_left.numel())
        else:
            self.time_left[env_ids] = self._draw(len(env_ids))

    def __call__(
        self,
        env: ManagerBasedRlEnv,
        env_ids: torch.Tensor | None,
        velocity_range: dict[str, tuple[float, float]],
        asset_cfg: Any,
    ) -> None:
        """The manager's per-step call (``env_ids`` None): timers and due pushes. Called with
        ``env_ids`` (by hand, as mjlab's interval manager calls its function), it pushes those
        envs now and leaves the timers alone."""
        del velocity_range  # read once in __init__
        if env_ids is None:
            self.time_left -= env.step_dt
            due = self.time_left < 1e-6
            self.time_left = torch.where(due, self._draw(env.num_envs), self.time_left)
        else:
            due = torch.zeros(env.num_envs, dtype=torch.bool, device=self.device)
            due[env_ids] = True
        asset = env.scene[asset_cfg.name]
        offset = self.lo + self.span * torch.rand(env.num_envs, 6, device=self.device)
        vel_w = asset.data.root_link_vel_w + offset
        data = asset.data
        idx = data.indexing
        quat_w = data.data.qpos[:, idx.free_joint_q_adr[3:7]]
        pushed = torch.cat([vel_w[:, :3], quat_apply_inverse(quat_w, vel_w[:, 3:])], dim=-1)
        old = data.data.qvel[:, idx.free_joint_v_adr]
        data.data.qvel[:, idx.free_joint_v_adr] = torch.where(due.unsqueeze(-1), pushed, old)
