"""The G1 action's joint groups: legs (hip, knee, ankle), waist, arms (shoulder, elbow, wrist).

Exploration and its diagnostics are read per group (issue 56): the task needs the 12 leg
joints, while the 17 waist and arm joints take the same exploration noise and carry most of the
CLF's V at CPU scale (docs/signal.md). The groups are derived from the joint names in action
order, as mjlab's action terms resolve them (``target_names``), never from a typed index list:
the indices follow whatever order mjlab gives the actuators.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:
    from mjlab.envs import ManagerBasedRlEnv

JOINT_GROUPS: tuple[str, ...] = ("legs", "waist", "arms")
"""The groups, in the order every table and column names them."""

GROUP_PATTERNS: dict[str, str] = {
    "legs": r".*_(hip|knee|ankle)_.*",
    "waist": r"waist_.*",
    "arms": r".*_(shoulder|elbow|wrist)_.*",
}
"""A joint belongs to the group whose pattern fully matches its name (exactly one must)."""

G1_GROUP_SIZES: dict[str, int] = {"legs": 12, "waist": 3, "arms": 14}
"""The 29-DoF G1's joints per group (mjlab's ``unitree_g1``)."""


def group_of(name: str) -> str:
    """The group of one joint name; ValueError if no group or more than one matches."""
    hits = [g for g in JOINT_GROUPS if re.fullmatch(GROUP_PATTERNS[g], name)]
    if len(hits) != 1:
        raise ValueError(
            f"joint {name!r} matches {len(hits)} of the joint groups "
            f"{dict(GROUP_PATTERNS)} (exactly one must)"
        )
    return hits[0]


def joint_groups(names: Sequence[str]) -> dict[str, list[int]]:
    """group -> the action indices of its joints, for joint ``names`` in action order."""
    out: dict[str, list[int]] = {g: [] for g in JOINT_GROUPS}
    for i, name in enumerate(names):
        out[group_of(name)].append(i)
    return out


def action_joint_names(env: ManagerBasedRlEnv) -> list[str]:
    """The joint names of the env's action vector, in its order (every active action term's
    ``target_names``, in the action manager's order)."""
    manager = env.action_manager
    names: list[str] = []
    for term in manager.active_terms:
        names.extend(str(n) for n in manager.get_term(term).target_names)
    if len(names) != manager.total_action_dim:
        raise ValueError(
            f"the action terms name {len(names)} joints for {manager.total_action_dim} actions"
        )
    return names


def group_index(names: Sequence[str], device: str | torch.device = "cpu") -> torch.Tensor:
    """(A,) long: each action's group as its position in :data:`JOINT_GROUPS` (built once,
    for per-group reductions by ``index_add`` / ``scatter``)."""
    return torch.tensor([JOINT_GROUPS.index(group_of(n)) for n in names], device=device)


def per_joint(names: Sequence[str], value: Mapping[str, float]) -> torch.Tensor:
    """(A,) float: each joint's group ``value`` (group -> number), in action order."""
    missing = [g for g in JOINT_GROUPS if g not in value]
    if missing:
        raise ValueError(f"no value for the joint groups {missing}")
    return torch.tensor([float(value[group_of(n)]) for n in names])


def group_means(x: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """(..., G) mean of ``x`` (..., A) over each group's actions (``index`` from
    :func:`group_index`); a group without actions reads NaN."""
    sums = torch.zeros((*x.shape[:-1], len(JOINT_GROUPS)), dtype=x.dtype, device=x.device)
    sums.index_add_(-1, index, x)
    counts = torch.bincount(index, minlength=len(JOINT_GROUPS)).to(x.dtype)
    return sums / counts
