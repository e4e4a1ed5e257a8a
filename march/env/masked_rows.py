"""Per-env state tensors written where a mask says, one ``index_put`` per dtype (issues 20, 41).

The reference command plans a fixed-size batch of envs every update and applies the new step
only to the envs that are due (:mod:`march.env.replan_queue`). Written the plain way, each state
tensor costs a gather, a ``where`` and an ``index_put`` per update (~57 kernel launches for its
19 tensors). :class:`MaskedRows` keeps the tensors of one dtype as column blocks of one
(E + 1)-row buffer: the tensor an owner keeps is a view of the first E rows of its block, and
the rows of the batch that are not applied are written to row E, which nothing reads. A write is
then one ``cat`` of the new values and one ``index_put`` per dtype (float, bool): 5 ops for the
19 tensors (20 with one ``index_put`` each). Plain torch; no host sync.
"""

from __future__ import annotations

import math

import torch


class MaskedRows:
    """The (E + 1)-row storage of named per-env tensors of ``owners`` (name -> (object,
    attribute)); each attribute is replaced by a view of the first E rows of its dtype's buffer
    (same shape, dtype and values; in-place writes through it land in the buffer)."""

    def __init__(self, num_envs: int, owners: dict[str, tuple[object, str]]) -> None:
        self.num_envs = num_envs
        groups: dict[torch.dtype, list[tuple[str, object, str, torch.Tensor]]] = {}
        for name, (owner, attr) in owners.items():
            value = getattr(owner, attr)
            if value is None:
                continue
            groups.setdefault(value.dtype, []).append((name, owner, attr, value))
        self.buffers: list[tuple[torch.Tensor, list[str]]] = []
        """Per dtype: the (E + 1, W) buffer and the names of its column blocks, in order."""
        self.storage: dict[str, torch.Tensor] = {}
        """Per name: the (E + 1, ...) rows of its block (a view of the buffer)."""
        for members in groups.values():
            flat = [v.reshape(num_envs, -1) for _, _, _, v in members]
            rows = torch.cat(flat, dim=1)
            buffer = torch.cat([rows, rows[:1]]).contiguous()
            start = 0
            for (name, owner, attr, value), cols in zip(members, flat, strict=True):
                width = cols.shape[1]
                block = buffer[:, start : start + width]
                shaped = (
                    block.view(num_envs + 1, *value.shape[1:]) if value.dim() > 1 else block[:, 0]
                )
                self.storage[name] = shaped
                setattr(owner, attr, shaped[:num_envs])
                start += width
            self.buffers.append((buffer, [name for name, _, _, _ in members]))
        self._widths = {n: math.prod(t.shape[1:]) for n, t in self.storage.items()}

    def write(
        self, env_ids: torch.Tensor, apply: torch.Tensor, values: dict[str, torch.Tensor]
    ) -> None:
        """Set row ``env_ids[i]`` of every tensor to ``values[name][i]`` where ``apply[i]``;
        the other rows are left as they were."""
        rows = torch.where(apply, env_ids, self.num_envs)
        n = env_ids.shape[0]
        for buffer, names in self.buffers:
            parts = [values[name].reshape(n, self._widths[name]).to(buffer.dtype) for name in names]
            buffer[rows] = parts[0] if len(parts) == 1 else torch.cat(parts, dim=1)
