"""The configuration of the ``reference`` command term (:mod:`march.env.reference_command`):
touchdown rules, the per-update planner batch, the planner / reference / HLIP / CLF sections."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from mjlab.managers.command_manager import CommandTermCfg

from march.clf.lyapunov import ClfCfg
from march.reference.hlip import HlipCfg
from march.reference.planner import PlannerCfg
from march.reference.trajectory import ReferenceCfg

if TYPE_CHECKING:
    from mjlab.envs import ManagerBasedRlEnv

    from march.env.reference_command import ReferenceCommand


@dataclass(kw_only=True)
class ReferenceCommandCfg(CommandTermCfg):
    """Configuration of the ``reference`` command term (defaults: author values, SPEC §2)."""

    resampling_time_range: tuple[float, float] = (1.0e9, 1.0e9)
    """Only episode resets restart the term (no timed resampling)."""
    entity_name: str = "robot"
    velocity_command: str = "twist"
    """The velocity command term this one reads (v_D and the yaw rate)."""
    contact_sensor: str = "feet_ground_contact"
    foot_bodies: tuple[str, str] = ("left_ankle_roll_link", "right_ankle_roll_link")
    """Contact-sensor primaries of the left and right foot."""
    foot_sites: tuple[str, str] = ("left_foot", "right_foot")
    """Sites tracked as the feet (sole level)."""
    touchdown_min_fraction: float = 0.6
    """A swing-foot contact counts as touchdown from tau >= this x planned duration (author 0.6)."""
    touchdown_timeout_fraction: float = 1.5
    """No touchdown by tau >= this x planned duration: restart the step from the same stance."""
    stance_tie_m: float = 0.01
    """At reset, feet within this along the course count as level (then the left foot stands)."""
    replan_capacity_fraction: float = 0.125
    """Share of the envs whose touchdown or timeout can be planned in one update (the fixed
    size of the per-step planner batch; module docstring, "Replanning without host syncs")."""
    replan_capacity_min: int = 8
    """The per-update planner batch holds at least this many envs (or all of them)."""
    compile_math: bool = False
    """``torch.compile`` (dynamic shapes) :func:`reference_at` (``compute.compile_math``)."""
    planner_seed: int | None = 0
    """Seed of the planner's random draws (torch.Generator on the env device)."""
    planner: PlannerCfg = field(default_factory=PlannerCfg)
    reference: ReferenceCfg = field(default_factory=ReferenceCfg)
    hlip: HlipCfg = field(default_factory=HlipCfg)
    clf: ClfCfg = field(default_factory=lambda: ClfCfg(dclf_clip=1.0))
    """CLF outputs and normalisers. r_dclf is clipped at -1 (``dclf_clip = 1.0``, the author's
    ``clip(., 0, 1)``; the paper prints no clip): unclipped, under the initial policy's action
    noise (std 1) the weighted r_dclf averages about -22 per step against +3.7 for the weighted
    r_clf (8 envs, 150 steps), so the decrease term swamps every other signal; clipped it
    averages about -0.5."""

    def capacity(self, num_envs: int) -> int:
        """Envs planned per update for touchdowns and timeouts, for ``num_envs`` envs."""
        by_share = math.ceil(self.replan_capacity_fraction * num_envs)
        return min(num_envs, max(self.replan_capacity_min, by_share))

    def build(self, env: ManagerBasedRlEnv) -> ReferenceCommand:
        from march.env.reference_command import ReferenceCommand

        return ReferenceCommand(self, env)

    def __post_init__(self) -> None:
        if not 0.0 <= self.touchdown_min_fraction < self.touchdown_timeout_fraction:
            raise ValueError("need 0 <= touchdown_min_fraction < touchdown_timeout_fraction")
        if not 0.0 < self.replan_capacity_fraction <= 1.0 or self.replan_capacity_min < 1:
            raise ValueError("need 0 < replan_capacity_fraction <= 1 and replan_capacity_min >= 1")
        if not math.isclose(self.planner.step_width, self.hlip.step_width):
            raise ValueError("planner.step_width and hlip.step_width must agree")
