"""The footstep planner's configuration (:class:`PlannerCfg`, author values where SPEC.md gives
them) and its numerical slack: the one module every part of the planner imports (its tables,
search inputs, cost and search: :mod:`march.reference.planner`). Plain Python and torch."""

from __future__ import annotations

from dataclasses import dataclass

import torch

EPS = 1e-5
"""Slack of the margin tests [m]: clamped footholds pass ``Footholds.contains`` in float32."""


@dataclass
class PlannerCfg:
    """Footstep planner parameters (author values where SPEC.md gives them)."""

    num_steps: int = 4
    """Horizon N: planned steps per replan (paper: 4)."""
    num_rollouts: int = 16
    """Greedy random-shooting rollouts R (paper: 16); rollout 0 is noise-free greedy."""
    duration_range: tuple[float, float] = (0.45, 0.7)
    """Shortest and longest step duration dt [s] (author)."""
    num_durations: int = 7
    """Number of evenly spaced duration candidates in ``duration_range`` (author: 7)."""
    step_width: float = 0.25
    """Nominal lateral distance between the feet [m] (author y_nom); keep equal to HlipCfg."""
    max_step: float = 0.85
    """Upper bound on the horizontal step length ||l|| [m] (author)."""
    min_step_forward: float = -0.25
    """Lower bound on the step component along the course [m] (a short backward step is allowed)."""
    min_lateral: float = 0.08
    """Least lateral distance of the landing foot to its own side of the stance foot [m]."""
    max_lateral: float = 0.45
    """Largest lateral distance of the landing foot from the stance foot [m]."""
    max_step_height: float = 0.3
    """Largest |height change| between stance and landing stone tops [m]."""
    stone_margin: float = 0.04
    """Hard margin: a foothold keeps at least this distance to every stone edge [m]."""
    edge_clearance: float = 0.1
    """Soft margin: footholds closer than this to an edge pay the edge cost [m] (author)."""
    edge_cost: float = 100.0
    """Edge cost weight; c_edge = edge_cost * (max(0, clearance - d_edge) / clearance)^2 (author)."""
    w_velocity: float = 1.0
    """Weight of ||v_i - v_D||^2 [1/(m/s)^2] (paper: 1)."""
    w_time: float = 0.45
    """Step-time regulariser weight on (dt - T_nom)^2 [1/s^2] (author's extra, not the paper's:
    mostly breaks ties toward the middle duration on open ground). 0 = paper cost."""
    num_candidate_stones: int = 8
    """M: stones per step nearest to the nominal foothold that are searched."""
    samples_per_stone: int = 4
    """K: random footholds drawn uniformly on each searched stone (with the hard margin)."""
    fuse_candidates: bool | None = None
    """No effect since issue 41 (kept so that configs that set it still load): the search scores
    both candidate groups in one pass per term on every device (the plans were the same)."""
    explore_temperature: float = 0.2
    """Softmin temperature of the randomised rollouts [cost units]; 0 makes all rollouts greedy."""
    infeasible_cost: float = 1.0e4
    """Cost added per violated step; keeps costs finite and ranks least-violating fallbacks."""
    pace_fraction: float = 0.5
    """rho: a step keeps pace when its advance along the course is at least rho * v_D * dt
    (v_D the command's component along the course, dt the step's duration). 0 disables the
    progress term (the paper's cost alone, which steps in place before a far stone). 0.5 leaves
    the velocity term room to average the pace over short and long steps (0.9 made walks on the
    easiest courses 20% faster than commanded) and still rules out steps in place."""
    pace_cost: float = 1.0e3
    """Cost per step of missing the pace entirely: pace_cost * max(0, rho v_D dt - advance) /
    (rho v_D dt), charged only while the goal platform lies ahead of the stance foot. Larger than
    any edge + velocity cost (<= ~110) so a step that keeps pace always beats one that does not,
    smaller than ``infeasible_cost`` so a feasible short step still beats an infeasible one."""

    @property
    def nominal_duration(self) -> float:
        """T_nom: the middle of ``duration_range`` [s] (a candidate when num_durations is odd)."""
        return 0.5 * (self.duration_range[0] + self.duration_range[1])

    def duration_grid(
        self, device: torch.device | str = "cpu", dtype=torch.float32
    ) -> torch.Tensor:
        """(num_durations,) candidate step durations [s]."""
        return torch.linspace(*self.duration_range, self.num_durations, device=device, dtype=dtype)
