"""Episode-end bookkeeping kept on the device: no ``.item()`` per term and reset.

mjlab's ``TerminationManager.reset`` reads each termination term's count of ended envs with
``.item()`` (one host sync per term on every step in which an env resets: on a GPU with
thousands of envs, every step), and its ``CurriculumManager.reset`` reads each tensor a
curriculum term returns the same way. march configures both managers' terms, so it keeps their
episode-end logs on the device instead:

- :func:`keep_termination_counts_on_device` replaces the env's termination manager's ``reset``
  with mjlab's own, returning the same counts as 0-d tensors (``env.extras["log"]`` then holds
  tensors, as march's ``reference`` term's metrics already are; march's runners read none of
  them);
- march's curriculum term (``march.env.course.course_levels``) returns nothing to log: the
  runners log ``mean_terrain_level`` themselves.
"""

from __future__ import annotations

from typing import Any

import torch


def keep_termination_counts_on_device(env: Any) -> None:
    """``env.termination_manager.reset`` as mjlab's, its counts left as 0-d device tensors."""
    tm = env.termination_manager

    def reset(env_ids: torch.Tensor | slice | None = None) -> dict[str, torch.Tensor]:
        ids = slice(None) if env_ids is None else env_ids
        extras = {
            "Episode_Termination/" + key: torch.count_nonzero(dones[ids])
            for key, dones in tm._term_dones.items()
        }
        for term_cfg in tm._class_term_cfgs:
            term_cfg.func.reset(env_ids=ids)
        return extras

    tm.reset = reset
