"""An upper bound on the sizes a run may ask for: a lower-bound memory estimate of its envs and
buffers, against the memory of the chosen device, checked before anything is built.

The estimate counts only what a run surely holds, so it never refuses a run that fits:

- simulator state, :data:`SIM_BYTES_PER_ENV` per env (MuJoCo Warp's ``Data`` for mjlab's G1 with
  the velocity task's ``njmax`` 1500 / ``nconmax`` 35, summed over its arrays: 48.4 KB per
  world, measured with ``mujoco_warp.put_data``; the stones' geoms and the sensors come on top),
  for the training envs and the evaluation envs (both exist at once);
- one observation frame of :data:`PROPRIO_FLOATS` floats per history step (actor and critic)
  per env, and the depth image for the student;
- the rollout storage: per env and step of an iteration, the observations (actor and critic),
  actions, log-probability, value, return and advantage (teacher) or the student's inputs and
  the teacher's action mean and std (distillation); the larger of the two stages counts.

A run whose estimate exceeds the device's memory (the machine's RAM for ``cpu``, the GPU's for
``cuda``) is refused in one line with the estimate and the largest size that would fit.
Pure data: torch is imported only to ask a CUDA device its size.
"""

from __future__ import annotations

import os
from typing import Any

from march.errors import ConfigError

SIM_BYTES_PER_ENV = 48_400
"""MuJoCo Warp ``Data`` of one G1 world (njmax 1500, nconmax 35), bytes (a lower bound)."""
PROPRIO_FLOATS = 96
"""One proprioceptive frame: angular velocity 3, gravity 3, command 3, joint positions,
velocities and last actions 29 each (a lower bound on every observation group's frame)."""
ACTIONS = 29
FLOAT = 4


def estimate(cfg: Any) -> dict[str, int]:
    """Bytes by part (a lower bound) for ``cfg`` (a MarchConfig or anything shaped like one)."""
    c, e = cfg.compute, cfg.env
    n, n_eval = int(c.num_envs), int(c.eval_num_envs)
    frame = PROPRIO_FLOATS * int(e.history_length) * FLOAT
    depth = int(cfg.depth.width) * int(cfg.depth.height) * FLOAT
    teacher_step = 2 * frame + (3 * ACTIONS + 4) * FLOAT
    student_step = frame + depth + 2 * ACTIONS * FLOAT
    rollout = max(
        int(cfg.teacher.num_steps_per_env) * teacher_step,
        int(cfg.distill.num_steps_per_env) * student_step,
    )
    return {
        "simulator state": (n + n_eval) * SIM_BYTES_PER_ENV,
        "observations": (n + n_eval) * (2 * frame + depth),
        "rollout storage": n * rollout,
    }


def device_bytes(device: str) -> int | None:
    """Memory of ``device`` (bytes), or None where it cannot be asked (CUDA not available)."""
    if device.startswith("cuda"):
        import torch

        if not torch.cuda.is_available():
            return None
        index = torch.device(device).index
        return int(torch.cuda.get_device_properties(index or 0).total_memory)
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError):
        return None


def human(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB", "TB", "PB"):
        if abs(n) < 1000 or unit == "PB":
            return f"{n:.3g} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1000
    return f"{n:.3g} PB"


def check_memory(cfg: Any, where: str = "") -> None:
    """Raise one line when the lower-bound estimate exceeds the device's memory."""
    parts = estimate(cfg)
    total = sum(parts.values())
    have = device_bytes(cfg.compute.device)
    if have is None or total <= have:
        return
    c = cfg.compute
    per_env = total / max(c.num_envs + c.eval_num_envs, 1)
    fits = int(have // max(per_env, 1))
    biggest = max(parts, key=parts.__getitem__)
    sizes = (
        f"compute.num_envs={c.num_envs} compute.eval_num_envs={c.eval_num_envs} "
        f"env.history_length={cfg.env.history_length} "
        f"teacher.num_steps_per_env={cfg.teacher.num_steps_per_env} "
        f"distill.num_steps_per_env={cfg.distill.num_steps_per_env}"
    )
    raise ConfigError(
        f"{where}{sizes} need at least {human(total)} ({biggest} {human(parts[biggest])}; "
        f"about {human(per_env)} per env), but {c.device} has {human(have)}: about {fits} envs "
        "fit at these sizes; lower compute.num_envs / compute.eval_num_envs or the sizes"
    )
