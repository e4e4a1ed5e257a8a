"""Random one-step reference states (``StepState``) for the swing-foot shaping tests: every
field drawn from ``g`` in float64 over ranges a planned step can take."""

from __future__ import annotations

import torch

from march.reference.trajectory import StepState

F64 = torch.float64


def random_steps(e: int, g: torch.Generator) -> StepState:
    """``e`` random steps (durations 0.45-0.7 s, CoM heights 0.6-0.67 m)."""

    def r(*shape):
        return torch.rand(*shape, generator=g, dtype=F64)

    return StepState(
        stance_pos=r(e, 3) - 0.5,
        stance_is_left=r(e) > 0.5,
        swing_start=r(e, 3) - 0.5,
        target=r(e, 3),
        next_target=r(e, 3) + 0.5,
        duration=0.45 + 0.25 * r(e),
        next_duration=0.45 + 0.25 * r(e),
        yaw0=2 * r(e) - 1,
        yaw_rate=r(e) - 0.5,
        axis=torch.nn.functional.normalize(r(e, 2) + 0.1, dim=-1),
        com_from_pos=r(e, 3),
        com_from_vel=r(e, 3) - 0.5,
        pelvis_from_pos=0.1 * r(e, 2),
        pelvis_from_vel=r(e, 2) - 0.5,
        z0=0.6 + 0.07 * r(e),
    )
