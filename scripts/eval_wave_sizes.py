"""One evaluation in waves of different sizes: how far apart its per-rollout rows are.

Every random number of an evaluation rollout is keyed by (seed, rollout index)
(march.env.rollout_draws), so what is left between wave sizes is mujoco_warp's contact solve,
which is not batch-invariant in its last bits (docs/scaling.md, "Evaluation over N ranks"). The
policy is a fixed random linear map of the actor observation (seeded), so the actions depend on
every observed number; the smoke eval env, one process.

    python scripts/eval_wave_sizes.py [--rollouts 8] [--sizes 8 2] [--seconds 2.0]
"""

from __future__ import annotations

import argparse

import torch


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rollouts", type=int, default=8)
    parser.add_argument("--sizes", type=int, nargs="+", default=[8, 2], help="wave sizes")
    parser.add_argument("--seconds", type=float, default=2.0, help="eval.episode_length_s")
    args = parser.parse_args()

    from march.config.cli import load
    from march.env.build import make_env
    from march.evaluation.protocol import rollout_metrics

    rows = {}
    for size in args.sizes:
        overrides = [f"compute.eval_num_envs={size}", f"eval.episode_length_s={args.seconds}"]
        cfg = load(["compute=smoke", "reward=clf", *overrides])
        env = make_env(cfg, "eval")
        weights = torch.randn(
            env.observation_manager.group_obs_dim["actor"][0],
            env.action_manager.total_action_dim,
            generator=torch.Generator().manual_seed(0),
        )

        def policy(obs, w=weights * 0.05):
            return torch.tanh(obs["actor"] @ w)

        rows[size] = rollout_metrics(env, policy, args.rollouts)
        env.close()
    ref, *others = args.sizes
    print(f"{args.rollouts} rollouts of {args.seconds} s; waves of {ref} against {others}")
    for size in others:
        for name in ("distance_m", "episode_steps", "abs_torque_nm", "reward"):
            a, b = rows[ref][name].double(), rows[size][name].double()
            diff = (a - b).abs().nan_to_num(0.0)
            same = int((diff == 0).sum())
            print(
                f"  waves of {size:>3}: {name:<14} identical {same}/{len(a)}, "
                f"|diff| median {diff.median():.2e}, max {diff.max():.2e} (rollout {int(diff.argmax())})"
            )


if __name__ == "__main__":
    main()
