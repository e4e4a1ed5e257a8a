"""How far the CoM reference jumps at real touchdowns in the teacher env (issue 55), for each
``reference.com_anchoring``: p50 / p90 / max of |y_ref after - y_ref before| at the same instant
(the old step's reference at the touchdown against the new step's at tau = 0), per CoM axis, in
position and velocity, over every touchdown (and, separately, every timeout restart).

    python scripts/reference_jumps.py [--envs 10] [--steps 300] [--std 0.3] [overrides ...]

Defaults: compute=smoke, dr=none; the envs spread over the curriculum's levels (env i on level
i mod levels); actions 0.3 N(0, 1) (seeded): the robot stumbles, lifts feet and lands them.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from march.config.cli import load
from march.env.build import make_env
from march.env.reference_command import reference_term

AXES = ("com_x", "com_y", "com_z")


def spread_levels(env) -> int:
    """Put env i on curriculum level i mod levels and reset; the number of levels."""
    terrain = env.scene.terrain
    rows = terrain.terrain_origins.shape[0]
    levels = torch.arange(env.num_envs, device=env.device) % rows
    terrain.terrain_levels[:] = levels.to(terrain.terrain_levels.dtype)
    terrain.env_origins[:] = terrain.terrain_origins[terrain.terrain_levels, terrain.terrain_types]
    counter, env.common_step_counter = env.common_step_counter, 0  # no curriculum move
    env.reset()
    env.common_step_counter = counter
    return rows


def jumps(env, steps: int, std: float, seed: int = 0) -> dict[str, np.ndarray]:
    """(n, 6) |jump| of (x, y, z position, x, y, z velocity) at touchdowns and at timeouts."""
    term = reference_term(env)
    gen = torch.Generator(device=env.device).manual_seed(seed)
    n_act = env.action_manager.total_action_dim
    out: dict[str, list[np.ndarray]] = {"touchdown": [], "timeout": []}
    for _ in range(steps):
        before = term._next_ref
        tds, fcs = term.touchdown_count.clone(), term.forced_count.clone()
        action = std * torch.randn(env.num_envs, n_act, device=env.device, generator=gen)
        _, _, terminated, truncated, _ = env.step(action)
        if before is None:
            continue
        keep = ~(terminated | truncated)
        old = torch.cat([before[1][:, :3], before[2][:, :3]], -1)
        new = torch.cat([term.y_ref_pos[:, :3], term.y_ref_vel[:, :3]], -1)
        gap = (new - old).abs()
        for name, mask in (
            ("touchdown", keep & (term.touchdown_count > tds)),
            ("timeout", keep & (term.forced_count > fcs)),
        ):
            out[name].append(gap[mask].cpu().numpy())
    return {k: np.concatenate(v) if v else np.zeros((0, 6)) for k, v in out.items()}


def table(gaps: np.ndarray) -> dict[str, list[float]]:
    """p50 / p90 / max per column (positions in mm, velocities in m/s)."""
    if len(gaps) == 0:
        return {}
    cols = {}
    for j, axis in enumerate(AXES):
        for kind, col, scale in (("pos_mm", j, 1000.0), ("vel_mps", j + 3, 1.0)):
            v = gaps[:, col] * scale
            cols[f"{axis}_{kind}"] = [round(float(np.quantile(v, q)), 4) for q in (0.5, 0.9)]
            cols[f"{axis}_{kind}"].append(round(float(v.max()), 4))
    return cols


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--envs", type=int, default=10)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--std", type=float, default=0.3)
    ap.add_argument("overrides", nargs="*")
    args = ap.parse_args()
    result = {}
    for anchoring in ("stance", "continuous"):
        cfg = load(
            ["compute=smoke", "dr=none", f"reference.com_anchoring={anchoring}", *args.overrides]
        )
        env = make_env(cfg, "teacher", num_envs=args.envs)
        levels = spread_levels(env)
        gaps = jumps(env, args.steps, args.std)
        env.close()
        result[anchoring] = {
            "levels": levels,
            "touchdowns": len(gaps["touchdown"]),
            "timeouts": len(gaps["timeout"]),
            "touchdown_jump_p50_p90_max": table(gaps["touchdown"]),
            "timeout_jump_p50_p90_max": table(gaps["timeout"]),
        }
        print(anchoring, json.dumps(result[anchoring], indent=1), flush=True)


if __name__ == "__main__":
    main()
