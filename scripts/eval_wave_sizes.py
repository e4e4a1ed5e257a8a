"""One evaluation in waves of different sizes: how far apart its per-rollout rows are.

Every random number of an evaluation rollout is keyed by (seed, rollout index)
(march.env.rollout_draws), so what is left between wave sizes is mujoco_warp's contact solve,
which is not batch-invariant in its last bits (docs/scaling.md, "Evaluation over N ranks"). The
policy is a fixed random linear map of the actor observation (seeded), so the actions depend on
every observed number; the smoke eval env, one process.

    python scripts/eval_wave_sizes.py [--rollouts 8] [--sizes 8 2] [--seconds 2.0]
    python scripts/eval_wave_sizes.py --slots   # one state copied into every slot of a batch

``--slots``: the smoke eval env (no randomisation, no pushes) steps 8 zero-action steps, then
world 0's state is copied into every world and the physics recomputed: the accelerations of
identical worlds, by slot. Equal in every slot until the feet touch a stone; after that they
differ in their last bits by slot, which is why no split of rollouts into waves of another
size can reproduce the same floats.
"""

from __future__ import annotations

import argparse

import torch


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rollouts", type=int, default=8)
    parser.add_argument("--sizes", type=int, nargs="+", default=[8, 2], help="wave sizes")
    parser.add_argument("--seconds", type=float, default=2.0, help="eval.episode_length_s")
    parser.add_argument("--slots", action="store_true", help="identical worlds, by slot")
    args = parser.parse_args()
    if args.slots:
        slots()
        return

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


def slots(num_envs: int = 4, steps: int = 8) -> None:
    from march.config.cli import load
    from march.env.build import make_env

    off = ["eval.randomization=false", "eval.pushes=false", f"compute.eval_num_envs={num_envs}"]
    env = make_env(load(["compute=smoke", "reward=clf", *off]), "eval")
    env.reset()
    for _ in range(steps):
        env.step(torch.zeros(num_envs, env.action_manager.total_action_dim))
    data = env.sim.data
    data.qpos[:] = data.qpos[0:1].clone()
    data.qvel[:] = data.qvel[0:1].clone()
    env.sim.forward()
    diff = [(data.qacc[i] - data.qacc[0]).abs().max().item() for i in range(num_envs)]
    contacts = int(data.nacon[0]) if hasattr(data, "nacon") else -1
    print(f"{num_envs} identical worlds after {steps} steps, {contacts} contacts in the batch")
    print("  max |qacc - qacc of slot 0| by slot: " + ", ".join(f"{d:.2e}" for d in diff))
    env.close()


if __name__ == "__main__":
    main()
