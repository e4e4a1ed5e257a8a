"""One evaluation in waves of different sizes: how far apart its per-rollout rows are, and why.

Every random number of an evaluation rollout is keyed by (seed, rollout index)
(march.env.rollout_draws), so what could be left between wave sizes is the simulator. Probed
here (issue 57): mujoco_warp steps every world alone except for one thing, its Newton solver's
Hessian accumulation, whose summation order follows ``solver._jtdaj_groups_per_world(nworld,
njmax)``: 6 / 3 / 1 / 1 slots per world for 1 / 2 / 4 / 8 worlds on the CPU. Evaluation envs pin
it (march.env.solver_order); ``--unpinned`` shows the rows without the pin. The policy is a fixed
random linear map of the actor observation (seeded), so the actions depend on every observed
number, computed row by row (no matmul, whose BLAS kernel depends on the row count); the smoke
eval env, one process.

    python scripts/eval_wave_sizes.py [--rollouts 8] [--sizes 8 2] [--seconds 2.0] [--dr]
                                      [--unpinned]
    python scripts/eval_wave_sizes.py --slots [--sizes 8 4 2 1]   # one state in every slot
    python scripts/eval_wave_sizes.py --price [--sizes 2 8] [--compute gpu]  # the pin's cost

Default: domain randomisation and pushes off (``--dr``: on, as the evaluation protocol runs);
every column of the rollout rows is compared, wave size by wave size.

``--slots``: the smoke eval env (no randomisation, no pushes) steps 8 zero-action steps; then
world 0's whole per-world state (every mjwarp.Data array with a leading world axis: qpos, qvel,
act, ctrl, qacc_warmstart, ..., not only qpos and qvel) is copied into every world of batches
of each size and the physics recomputed (``forward``): the accelerations of identical worlds, by
slot and against the first batch, with the pin and without it, and in a reversed batch.

``--price``: the pin's cost on this machine with march.bench's interleaved timing
(``march.bench.env_speed.run_workload``): two teacher envs of each size, one stepped inside
``solver_order.pinned()``, timed in the same rounds.
"""

from __future__ import annotations

import argparse
import dataclasses
import json

import torch

from march.env import solver_order

ROW_COLUMNS = (
    "success",
    "fell",
    "distance_m",
    "episode_steps",
    "abs_torque_nm",
    "abs_ang_jerk",
    "reward",
)


def load_eval(size: int, seconds: float, dr: bool):
    from march.config.cli import load

    off = [] if dr else ["eval.randomization=false", "eval.pushes=false"]
    over = [f"compute.eval_num_envs={size}", f"eval.episode_length_s={seconds}", *off]
    return load(["compute=smoke", "reward=clf", *over])


def rows(args: argparse.Namespace) -> None:
    from contextlib import ExitStack

    from march.env.build import make_env
    from march.evaluation.protocol import rollout_metrics

    out = {}
    for size in args.sizes:
        with ExitStack() as stack:
            if args.unpinned:  # the pin reads SLOTS: set it to mujoco_warp's own count
                stack.enter_context(unpinned())
            env = make_env(load_eval(size, args.seconds, args.dr), "eval")
            weights = torch.randn(
                env.observation_manager.group_obs_dim["actor"][0],
                env.action_manager.total_action_dim,
                generator=torch.Generator().manual_seed(0),
            )

            def policy(obs, w=weights * 0.05):
                # row by row (a broadcast product summed per row), not a matmul: BLAS picks its
                # kernel and summation order by the batch's row count, which would make the
                # actions, not the env, depend on the wave size
                return torch.tanh((obs["actor"][:, :, None] * w[None]).sum(dim=1))

            out[size] = rollout_metrics(env, policy, args.rollouts)
            env.close()
    ref, *others = args.sizes
    print(
        f"{args.rollouts} rollouts of {args.seconds} s, DR and pushes {'on' if args.dr else 'off'}, "
        f"solver order {'unpinned' if args.unpinned else 'pinned'}; waves of {ref} against {others}"
    )
    for size in others:
        for name in [c for c in out[ref] if c not in ("level", "column")]:
            a, b = out[ref][name].double(), out[size][name].double()
            both_nan = a.isnan() & b.isnan()
            diff = (a - b).abs().masked_fill(both_nan, 0.0)
            same = int(((a == b) | both_nan).sum())
            worst = int(diff.nan_to_num(float("inf")).argmax())
            print(
                f"  waves of {size:>3}: {name:<16} identical {same}/{len(a)}, "
                f"|diff| max {diff.nan_to_num(float('inf')).max():.2e} (rollout {worst})"
            )


def trace(args: argparse.Namespace) -> None:
    """Where two wave sizes first part: rollouts 0 and 1 in a wave of ``sizes[0]`` and of
    ``sizes[1]``, step by step, the first step whose physics state (qpos, qvel) or actor
    observation differs, and which observation terms differ there."""
    from march.env.build import make_env
    from march.evaluation.protocol import rollout_metrics

    seen = {}
    for size in args.sizes[:2]:
        env = make_env(load_eval(size, args.seconds, args.dr), "eval")
        weights = torch.randn(
            env.observation_manager.group_obs_dim["actor"][0],
            env.action_manager.total_action_dim,
            generator=torch.Generator().manual_seed(0),
        )
        names = env.observation_manager.active_terms["actor"]
        dims = [
            int(torch.tensor(d).prod()) for d in env.observation_manager.group_obs_term_dim["actor"]
        ]
        rec = []
        data = env.sim.data

        def policy(obs, w=weights * 0.05, rec=rec, data=data):
            rec.append((data.qpos[:2].clone(), data.qvel[:2].clone(), obs["actor"][:2].clone()))
            return torch.tanh(obs["actor"] @ w)

        rollout_metrics(env, policy, 2)
        seen[size] = rec
        env.close()
    a, b = seen[args.sizes[0]], seen[args.sizes[1]]
    bounds = torch.tensor([0, *dims]).cumsum(0).tolist()
    for t, ((qa, va, oa), (qb, vb, ob)) in enumerate(zip(a, b, strict=False)):
        dq, dv, do = (float((x - y).abs().max()) for x, y in ((qa, qb), (va, vb), (oa, ob)))
        if dq or dv or do:
            terms = [
                f"{n} {float((oa[:, lo:hi] - ob[:, lo:hi]).abs().max()):.1e}"
                for n, lo, hi in zip(names, bounds[:-1], bounds[1:], strict=True)
                if not torch.equal(oa[:, lo:hi], ob[:, lo:hi])
            ]
            print(
                f"first difference at control step {t}: |qpos| {dq:.1e}, |qvel| {dv:.1e}, "
                f"|actor obs| {do:.1e}; observation terms differing: {', '.join(terms) or 'none'}"
            )
            return
    print(f"rollouts 0-1 identical over {min(len(a), len(b))} control steps")


class unpinned:
    """mujoco_warp's own slot count even inside ``solver_order.pinned()`` (for comparison)."""

    def __enter__(self):
        solver_order.install()
        self.slots, solver_order.SLOTS = solver_order.SLOTS, None
        return self

    def __exit__(self, *exc):
        solver_order.SLOTS = self.slots


def per_world(data) -> dict[str, torch.Tensor]:
    """Every array of an mjwarp.Data with a leading world axis (the state a world carries from
    step to step and what forward() recomputes), as torch views."""
    import warp as wp

    out = {}
    for f in dataclasses.fields(data):
        v = getattr(data, f.name)
        if isinstance(v, wp.array) and v.ndim >= 1 and v.shape[0] == data.nworld:
            out[f.name] = wp.to_torch(v)
    return out


def slots(args: argparse.Namespace, steps: int = 8) -> None:
    from march.env.build import make_env

    envs = {n: make_env(load_eval(n, args.seconds, False), "eval") for n in args.sizes}
    first = envs[args.sizes[0]]
    first.reset()
    for _ in range(steps):
        first.step(torch.zeros(first.num_envs, first.action_manager.total_action_dim))
    state = {k: v[0].clone() for k, v in per_world(first.sim.wp_data).items()}
    print(
        f"world 0 of {args.sizes[0]} after {steps} zero-action steps ({len(state)} per-world "
        f"arrays copied, incl. qacc_warmstart: {'qacc_warmstart' in state}); "
        f"{int(first.sim.wp_data.nacon.numpy()[0])} contacts in that batch"
    )
    for label, ctx in (("pinned", solver_order.pinned), ("unpinned", unpinned)):
        qacc = {}
        with ctx():
            for n, env in envs.items():
                for k, v in per_world(env.sim.wp_data).items():
                    if k in state:  # (a 1-world batch also lists its batch-wide counters)
                        v[:] = state[k]
                env.sim.forward()
                qacc[n] = wp_qacc(env).clone()
                slot = max(float((qacc[n][i] - qacc[n][0]).abs().max()) for i in range(n))
                line = (
                    f"  {label:>8}: batch of {n}: {solver_order.groups_per_world(n, 10**6)} "
                    f"slot(s) per world; max |qacc - slot 0| {slot:.2e}; vs batch of "
                    f"{args.sizes[0]} {float((qacc[n] - qacc[args.sizes[0]][0]).abs().max()):.2e}"
                )
                print(line)
    env = envs[args.sizes[0]]  # a reversed batch: world i's state in slot n - 1 - i
    before = {k: v.clone() for k, v in per_world(env.sim.wp_data).items()}
    with solver_order.pinned():
        for k, v in per_world(env.sim.wp_data).items():
            v[:] = before[k]
        env.sim.forward()
        forward = wp_qacc(env).clone()
        for k, v in per_world(env.sim.wp_data).items():
            v[:] = before[k].flip(0)
        env.sim.forward()
        back = wp_qacc(env).flip(0)
    print(
        f"  reversed batch of {env.num_envs}: max |qacc diff| {float((forward - back).abs().max()):.2e}"
    )
    for env in envs.values():
        env.close()


def wp_qacc(env) -> torch.Tensor:
    import warp as wp

    return wp.to_torch(env.sim.wp_data.qacc)


def price(args: argparse.Namespace) -> None:
    """Two teacher envs per size, one stepped pinned, timed in march.bench's interleaved rounds."""
    from march.bench.env_speed import run_workload
    from march.config.cli import load
    from march.env.build import make_env

    result = {}
    for n in args.sizes:
        cfg = load([f"compute={args.compute}", "reward=clf", f"compute.num_envs={n}"])
        # run_workload's two slots: "march_teacher" (here: pinned) and "bare_rough" (unpinned),
        # so its ratio_march_vs_rough is pinned / unpinned steps per second, same rounds
        envs = {
            "march_teacher": Pinned(make_env(cfg, "teacher")),
            "bare_rough": make_env(cfg, "teacher"),
        }
        opts = {"steps": args.steps, "rounds": 8, "threads": [1], "warmup_random": 10}
        opts |= {"op_steps": 0, "profile_steps": 0}
        run = run_workload(envs, "random", opts, 0, cfg.compute.device)
        sps = run["steps_per_s"]
        result[n] = {
            "pinned_steps_per_s": sps["march_teacher"],
            "unpinned_steps_per_s": sps["bare_rough"],
            "pinned_over_unpinned": run["ratio_march_vs_rough"],
        }
        for env in envs.values():
            env.close()
    print(json.dumps(result, indent=1))


class Pinned:
    """An env whose every step and reset runs inside ``solver_order.pinned()``."""

    def __init__(self, env):
        self.env = env

    def __getattr__(self, name):
        return getattr(self.env, name)

    def step(self, action):
        with solver_order.pinned():
            return self.env.step(action)

    def reset(self, *a, **k):
        with solver_order.pinned():
            return self.env.reset(*a, **k)

    def close(self):
        self.env.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rollouts", type=int, default=8)
    parser.add_argument("--sizes", type=int, nargs="+", default=None, help="wave sizes")
    parser.add_argument("--seconds", type=float, default=2.0, help="eval.episode_length_s")
    parser.add_argument("--dr", action="store_true", help="domain randomisation and pushes on")
    parser.add_argument("--unpinned", action="store_true", help="mujoco_warp's own slot count")
    parser.add_argument("--slots", action="store_true", help="identical worlds, by slot")
    parser.add_argument("--price", action="store_true", help="the pin's cost (march.bench)")
    parser.add_argument("--trace", action="store_true", help="the first step two sizes part")
    parser.add_argument("--steps", type=int, default=80, help="--price: timed steps per env")
    parser.add_argument("--compute", default="smoke", help="--price: the compute preset (gpu)")
    args = parser.parse_args()
    if args.sizes is None:
        args.sizes = [8, 4, 2, 1] if args.slots else [2, 8] if args.price else [8, 2]
    if min(args.sizes) < 1 or args.rollouts < 1 or args.seconds <= 0:
        parser.exit(2, "error: --sizes and --rollouts must be >= 1, --seconds > 0\n")
    if args.slots:
        slots(args)
    elif args.price:
        price(args)
    elif args.trace:
        trace(args)
    else:
        rows(args)


if __name__ == "__main__":
    main()
