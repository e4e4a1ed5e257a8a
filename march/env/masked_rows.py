"""Per-env state tensors written where a mask says, one ``index_put`` each (issue 20).

The reference command plans a fixed-size batch of envs every update and applies the new step
only to the envs that are due (:mod:`march.env.replan_queue`). Written the plain way, each state
tensor costs a gather, a ``where`` and an ``index_put`` per update (~57 kernel launches for its
19 tensors). :class:`MaskedRows` gives every tensor one spare row: the tensor an owner keeps is
the first E rows of an (E + 1)-row tensor, and the rows of the batch that are not applied are
written to row E, which nothing reads. Plain torch; no host sync.
"""

from __future__ import annotations

import torch


class MaskedRows:
    """The (E + 1)-row storage of named per-env tensors of ``owners`` (name -> (object,
    attribute)); each attribute is replaced by the first E rows of its storage."""

    def __init__(self, num_envs: int, owners: dict[str, tuple[object, str]]) -> None:
        self.num_envs = num_envs
        self.storage: dict[str, torch.Tensor] = {}
        for name, (owner, attr) in owners.items():
            value = getattr(owner, attr)
            if value is None:
                continue
            spare = torch.cat([value, value[:1]])
            self.storage[name] = spare
            setattr(owner, attr, spare[:num_envs])

    def write(
        self, env_ids: torch.Tensor, apply: torch.Tensor, values: dict[str, torch.Tensor]
    ) -> None:
        """Set row ``env_ids[i]`` of every tensor to ``values[name][i]`` where ``apply[i]``;
        the other rows are left as they were."""
        rows = torch.where(apply, env_ids, self.num_envs)
        for name, target in self.storage.items():
            target[rows] = values[name].to(target.dtype)
