"""Evaluation wall time of one checkpoint over 1 or N processes (the waves of
march.evaluation.sharding dealt to the ranks).

    python scripts/eval_speed.py teacher_ckpt=<file> eval.num_rollouts=8 compute.eval_num_envs=4
    torchrun --standalone --nproc_per_node=2 scripts/eval_speed.py <the same overrides>

Builds the eval env and the policy as ``march.train stage=eval`` does, runs the evaluation once
untimed (warm-up: kernels, caches), then times one evaluation between two barriers. Rank 0
prints one JSON line: ranks, rollouts, wave size, waves, seconds, env steps per second (all
ranks) and a digest of the per-rollout rows (equal digests: the same rows).
"""

from __future__ import annotations

import hashlib
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def main(overrides: list[str]) -> None:
    import torch

    from march.config.cli import load
    from march.env.build import make_env
    from march.evaluation.protocol import policy_from_checkpoint, rollout_metrics
    from march.evaluation.sharding import sharded_rollouts, waves
    from march.learn import distributed
    from march.store.checkpoint import load_checkpoint
    from march.store.gate import apply_policy_checkpoint

    cfg = load(["stage=eval", "eval.policy=teacher", *overrides])
    cfg, _ = apply_policy_checkpoint(cfg, overrides)
    d = distributed.init(cfg.compute.device, cfg.compute.dist_timeout_s)
    cfg = distributed.rank_config(cfg)
    if cfg.compute.torch_threads:
        torch.set_num_threads(cfg.compute.torch_threads)
    import dataclasses

    env = make_env(dataclasses.replace(cfg, seed=distributed.agree(cfg.seed)), "eval")
    payload = load_checkpoint(cfg.teacher_ckpt, "teacher", cfg.compute.device)
    policy = policy_from_checkpoint(env, cfg, "teacher", payload, cfg.teacher_ckpt)
    n = cfg.eval.num_rollouts
    sharded_rollouts(env, policy, n, rollout_metrics)  # warm-up
    distributed.barrier()
    t0 = time.perf_counter()
    per = sharded_rollouts(env, policy, n, rollout_metrics)
    distributed.barrier()
    seconds = time.perf_counter() - t0
    steps = int(per["episode_steps"].sum())
    digest = hashlib.sha1(
        b"".join(per[k].double().numpy().tobytes() for k in sorted(per))
    ).hexdigest()[:12]
    if d.main:
        row = {
            "ranks": d.world,
            "rollouts": n,
            "wave_size": env.num_envs,
            "waves": len(waves(n, env.num_envs)),
            "seconds": round(seconds, 2),
            "env_steps_per_s": round(steps / seconds, 1),
            "rows_digest": digest,
        }
        print(json.dumps(row), flush=True)
    env.close()
    distributed.shutdown()


if __name__ == "__main__":
    main(sys.argv[1:])
