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


def assert_fused_is_readable(st: StepState, cfg, g: torch.Generator, label: object = None) -> None:
    """The env's fused reference (``reference_outputs``) equals ``reference_at`` flattened, to
    1e-9 in float64, at 3 random instants per step of ``st`` up to 1.4 T (late touchdowns
    included), under ``cfg`` (a ``ReferenceCfg``)."""
    from march.reference.fused_reference import reference_outputs
    from march.reference.hlip import HlipCfg
    from march.reference.trajectory import reference_at

    e = st.duration.shape[0]
    tau = st.duration[:, None] * 1.4 * torch.rand(e, 3, generator=g, dtype=F64)
    pos, vel = reference_outputs(st, tau, cfg, HlipCfg(), 17)
    for j in range(3):
        want_pos, want_vel = reference_at(st, tau[:, j], cfg, HlipCfg(), 17).flatten()
        assert torch.allclose(pos[:, j], want_pos, atol=1e-9, rtol=0.0), label
        assert torch.allclose(vel[:, j], want_vel, atol=1e-9, rtol=0.0), label


def assert_reference_option_is_read(key: str, value: float, bad: float, domain: str) -> None:
    """``reference.<key>=value`` on the command line reaches the reference command term's
    config (the audit's and the env's), its default is 0 (the author's reference), and
    ``bad`` is refused in one ConfigError naming the ``domain`` (e.g. ``[0.0, 0.5]``)."""
    import re

    import pytest

    from march.audit.feasibility import reference_command_cfg
    from march.config.cli import load
    from march.config.schema import ConfigError

    ref = reference_command_cfg(load(["compute=smoke", f"reference.{key}={value}"]))
    assert getattr(ref.reference, key) == value
    assert getattr(reference_command_cfg(load(["compute=smoke"])).reference, key) == 0.0
    with pytest.raises(ConfigError, match=re.escape(domain)):
        load(["compute=smoke", f"reference.{key}={bad}"])


def shaped_and_plain(st: StepState, tau: torch.Tensor, key: str, value: float) -> tuple:
    """``reference_at`` of ``st`` at ``tau`` flattened (positions, rates) with
    ``ReferenceCfg(key=value)`` and with the default, after checking that ``key=0`` gives the
    default bit for bit: (shaped, plain)."""
    from march.reference.hlip import HlipCfg
    from march.reference.trajectory import ReferenceCfg, reference_at

    def flat(cfg: ReferenceCfg) -> tuple[torch.Tensor, torch.Tensor]:
        return reference_at(st, tau, cfg, HlipCfg(), 17).flatten()

    plain, off = flat(ReferenceCfg()), flat(ReferenceCfg(**{key: 0.0}))
    assert torch.equal(off[0], plain[0]) and torch.equal(off[1], plain[1]), key
    return flat(ReferenceCfg(**{key: value})), plain


def assert_only_these_change(shaped: tuple, plain: tuple, columns: list[int]) -> None:
    """Every output column but ``columns`` (positions and rates) equal bit for bit."""
    others = [i for i in range(plain[0].shape[-1]) if i not in columns]
    assert torch.equal(shaped[0][:, others], plain[0][:, others])
    assert torch.equal(shaped[1][:, others], plain[1][:, others])
