"""mjlab's twist / heading velocity command without a host sync per step.

mjlab's ``UniformVelocityCommand`` picks the envs it updates with ``nonzero()`` and
``any()`` (heading envs, world-frame envs, standing envs: three syncs per step), its base
``CommandTerm.compute`` finds the envs whose command is due with ``(time_left <= 0).nonzero()``
(one more), and its reset reads each episode metric with ``.item()``. On a GPU each stalls the
stream. :class:`SyncFreeVelocityCommand` computes the same command with masked writes:

- the per-step update (heading controller, world-frame rotation, standing envs) writes every
  env with ``torch.where`` on the same masks: the same numbers as mjlab's, bit for bit (but
  see the last paragraph);
- a reset resamples the given envs (a host-sized id tensor) with the same draws in the same
  order as mjlab's (forward-only envs masked, not selected): the same numbers for the same
  random state;
- a command due on time (``resampling_time_range`` elapsed) is resampled by drawing for every
  env and keeping the draws of the due envs: the same distribution (each due env's command is
  uniform over the same ranges, independent of the others), not the same random stream. march
  configures ``resampling_time_range`` = 1e9 s, longer than any episode, so in march's envs
  none falls due and the per-step path skips the test (a host-side config fact);
- episode metrics are returned as 0-d tensors on the device (as march's ``reference`` term's).

``init_velocity_prob`` > 0 (march sets 0: episodes start standing) keeps mjlab's own reset.
With a world-frame or standing share of 0 (march's config) the per-step update leaves that
branch out; mjlab's would still apply it to an env whose uniform draw was exactly 0.0
(``0.0 <= 0.0``: probability 2^-24 per draw), the one case where the two differ.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

import torch
from mjlab.tasks.velocity.mdp import UniformVelocityCommandCfg
from mjlab.tasks.velocity.mdp.velocity_command import UniformVelocityCommand
from mjlab.utils.lab_api.math import wrap_to_pi


class SyncFreeVelocityCommand(UniformVelocityCommand):
    """``UniformVelocityCommand`` with masked writes instead of selected envs (module docstring)."""

    cfg: SyncFreeVelocityCommandCfg

    def __init__(self, cfg: SyncFreeVelocityCommandCfg, env: Any) -> None:
        super().__init__(cfg, env)
        self._never_due = cfg.resampling_time_range[0] > env.max_episode_length_s
        """No command falls due within an episode (every reset draws the timer from
        ``resampling_time_range``, whose lower end is longer than an episode): the per-step
        path leaves the due test out (march's envs: 1e9 s)."""

    def compute(self, dt: float | torch.Tensor, env_ids: torch.Tensor | None = None) -> None:
        self._update_metrics()
        if env_ids is None:
            self.time_left -= dt
            if self._never_due:
                self._update_command(None)
                return
            due = self.time_left <= 0.0
        else:
            assert not isinstance(dt, torch.Tensor)
            self.time_left[env_ids] -= dt
            due = torch.zeros_like(self.is_heading_env)
            due[env_ids] = self.time_left[env_ids] <= 0.0
        self._resample_where(due)
        self._update_command(env_ids)

    def reset(self, env_ids: torch.Tensor | slice | None) -> dict[str, Any]:
        if self.cfg.init_velocity_prob > 0.0:
            return super().reset(env_ids)
        assert isinstance(env_ids, torch.Tensor)
        extras: dict[str, Any] = {}
        for name, value in self.metrics.items():
            extras[name] = value[env_ids].mean()
            value[env_ids] = 0.0
        self.command_counter[env_ids] = 0
        self._resample(env_ids)
        return extras

    def _resample_where(self, due: torch.Tensor) -> None:
        """Resample the envs where ``due`` is true, without selecting them: every env draws, the
        due ones keep their draws (the same distribution as mjlab's ``_resample``)."""
        fresh = torch.empty_like(self.time_left).uniform_(*self.cfg.resampling_time_range)
        self.time_left.copy_(torch.where(due, fresh, self.time_left))
        self.command_counter += due.to(self.command_counter.dtype)
        self._draw(torch.arange(self.num_envs, device=self.device), due)

    def _resample_command(self, env_ids: torch.Tensor) -> None:
        self._draw(env_ids, None)

    def _draw(self, env_ids: torch.Tensor, keep: torch.Tensor | None) -> None:
        """mjlab's ``_resample_command`` for ``env_ids``, draw for draw; with ``keep`` (a mask
        over ``env_ids``) only the rows where it is true take the new values."""
        n = len(env_ids)
        r = torch.empty(n, device=self.device)
        rng = self.cfg.ranges

        def put(dest: torch.Tensor, value: torch.Tensor) -> None:
            dest[env_ids] = value if keep is None else torch.where(keep, value, dest[env_ids])

        b = self.vel_command_b
        vx = r.uniform_(*rng.lin_vel_x).clone()
        vy = r.uniform_(*rng.lin_vel_y).clone()
        wz = r.uniform_(*rng.ang_vel_z).clone()
        if self.cfg.heading_command:
            assert rng.heading is not None
            put(self.heading_target, r.uniform_(*rng.heading).clone())
            put(self.is_heading_env, r.uniform_(0.0, 1.0) <= self.cfg.rel_heading_envs)
        put(self.is_standing_env, r.uniform_(0.0, 1.0) <= self.cfg.rel_standing_envs)
        put(self.is_world_env, r.uniform_(0.0, 1.0) <= self.cfg.rel_world_envs)
        # The world-frame reference is the draw before the forward-only change (as mjlab's).
        drawn = torch.stack((vx, vy, wz), dim=-1)
        forward = r.uniform_(0.0, 1.0) <= self.cfg.rel_forward_envs
        put(self.is_forward_env, forward)
        # Forward-only envs: positive lin_vel_x (at least 0.3), zero lateral and angular.
        vx = torch.where(forward, vx.abs().clamp(min=0.3), vx)
        zero = torch.zeros_like(vy)
        vy, wz = torch.where(forward, zero, vy), torch.where(forward, zero, wz)
        new = torch.stack((vx, vy, wz), dim=-1)
        if keep is None:
            self.vel_command_w[env_ids] = drawn
            b[env_ids] = new
        else:
            k = keep.unsqueeze(-1)
            self.vel_command_w[env_ids] = torch.where(k, drawn, self.vel_command_w[env_ids])
            b[env_ids] = torch.where(k, new, b[env_ids])

    def _update_command(self, env_ids: torch.Tensor | None = None) -> None:
        """mjlab's update on every env with masks (pure function of the state)."""
        del env_ids
        b = self.vel_command_b
        if self.cfg.heading_command:
            self.heading_error = wrap_to_pi(self.heading_target - self.robot.data.heading_w)
            steer = torch.clip(
                self.cfg.heading_control_stiffness * self.heading_error,
                min=self.cfg.ranges.ang_vel_z[0],
                max=self.cfg.ranges.ang_vel_z[1],
            )
            b[:, 2] = torch.where(self.is_heading_env, steer, b[:, 2])
        if self.cfg.rel_world_envs > 0.0:  # a config constant: no env is world-frame otherwise
            heading = self.robot.data.heading_w
            cos_h, sin_h = torch.cos(heading), torch.sin(heading)
            vx_w, vy_w = self.vel_command_w[:, 0], self.vel_command_w[:, 1]
            w = self.is_world_env
            b[:, 0] = torch.where(w, cos_h * vx_w + sin_h * vy_w, b[:, 0])
            b[:, 1] = torch.where(w, -sin_h * vx_w + cos_h * vy_w, b[:, 1])
        if self.cfg.rel_standing_envs > 0.0:  # a config constant, as the world share above
            standing = self.is_standing_env.unsqueeze(-1)
            b.masked_fill_(standing, 0.0)
            self.vel_command_w.masked_fill_(standing, 0.0)


@dataclass(kw_only=True)
class SyncFreeVelocityCommandCfg(UniformVelocityCommandCfg):
    """``UniformVelocityCommandCfg`` building :class:`SyncFreeVelocityCommand`."""

    def build(self, env: Any) -> SyncFreeVelocityCommand:
        return SyncFreeVelocityCommand(self, env)


def sync_free(cfg: UniformVelocityCommandCfg) -> SyncFreeVelocityCommandCfg:
    """The same command configuration, building :class:`SyncFreeVelocityCommand`."""
    return SyncFreeVelocityCommandCfg(
        **{f.name: getattr(cfg, f.name) for f in fields(cfg) if f.init}
    )
