"""``python -m march.bench <job>``: how fast march's env and planner are, as one JSON object.

    python -m march.bench env [compute.num_envs=64] [bench.steps=100] [bench.warmup=10]
    python -m march.bench planner [compute.num_envs=64] [bench.steps=100]

Both jobs compose the same config as ``march.train`` (Hydra ``key=value`` overrides). The
benchmark's own two options are not part of the config schema: ``bench.steps=N`` (timed steps,
default 100) and ``bench.warmup=N`` (untimed steps first, default 10) are taken off the command
line before the config is composed. Everything mjlab and warp print while building and compiling
goes to stderr, so stdout is the JSON object alone (``... | jq`` works).

``env``: on ``compute.device`` with ``compute.num_envs`` envs, one after another (each closed
before the next is built): (a) the march teacher env (``make_env(cfg, "teacher")``: stepping
stones, privileged observations, paper domain randomization and, for reward=clf, the
``reference`` command term that runs the footstep planner), (b) mjlab's bare
``Mjlab-Velocity-Rough-Unitree-G1`` and (c) bare ``Mjlab-Velocity-Flat-Unitree-G1`` (their
registered configs, only ``scene.num_envs`` and ``seed`` set). Each is reset and stepped with the
same seeded random actions (uniform in [-1, 1], one torch generator reseeded per env) for
``warmup`` steps, then ``steps`` timed steps. ``*_steps_per_s`` counts env steps (num_envs x
control steps) per second of wall time; ``ms_per_step`` is one batched control step;
``march_teacher_planner_*`` is the time the teacher env spent inside the planner.

``planner``: :func:`march.bench_planner.bench_planner` (``steps`` timed replans of all
``num_envs`` envs on synthetic courses), plus the march teacher env's step time measured in the
same run: ``planner_share_of_env_step`` = ms per full-batch replan / ms per env step (an upper
bound: only envs at a reset, touchdown or step timeout replan). ``in_env_*`` measures the
planner calls the teacher env itself made in its timed steps (random actions: mostly resets
after falls); ``walk_*`` estimates a walking robot's share: touchdown rate = control step / mean
step duration of the planner's own walks over generated courses, times one replan of that many
envs.
"""

from __future__ import annotations

import contextlib
import gc
import json
import math
import os
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any

from march.cli import fail, run_tool
from march.config import MarchConfig

USAGE = (
    "usage: python -m march.bench env|planner [compute.num_envs=64] [compute.device=...] "
    "[bench.steps=100] [bench.warmup=10] [key=value ...]"
)
BENCH_DEFAULTS = {"steps": 100, "warmup": 10}
ROUGH_TASK = "Mjlab-Velocity-Rough-Unitree-G1"
FLAT_TASK = "Mjlab-Velocity-Flat-Unitree-G1"


def pop_bench_options(argv: Sequence[str]) -> tuple[list[str], dict[str, int]]:
    """Split ``bench.steps=`` / ``bench.warmup=`` off the overrides (they are not config keys)."""
    rest: list[str] = []
    opts = dict(BENCH_DEFAULTS)
    for arg in argv:
        if not arg.startswith("bench."):
            rest.append(arg)
            continue
        key, _, value = arg[len("bench.") :].partition("=")
        if key not in opts:
            fail(f"unknown benchmark option {arg!r}; use bench.steps=N or bench.warmup=N")
        try:
            n = int(value)
        except ValueError:
            fail(f"{arg}: expected an integer")
        if n < (1 if key == "steps" else 0):
            fail(f"{arg}: bench.steps must be >= 1 and bench.warmup >= 0")
        opts[key] = n
    return rest, opts


@contextlib.contextmanager
def stdout_to_stderr() -> Iterator[None]:
    """Send everything written to stdout (Python and C level: warp, mujoco) to stderr."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        os.dup2(2, 1)
        with contextlib.redirect_stdout(sys.stderr):
            yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


def _sync(device: str) -> None:
    import torch

    if device.startswith("cuda"):
        torch.cuda.synchronize()


def _free(device: str) -> None:
    import torch

    gc.collect()
    if device.startswith("cuda"):
        torch.cuda.empty_cache()


def bare_env(task: str, cfg: MarchConfig) -> Any:
    """mjlab's registered task ``task`` with only num_envs and seed changed."""
    from mjlab.envs import ManagerBasedRlEnv
    from mjlab.tasks.registry import load_env_cfg

    env_cfg = load_env_cfg(task)
    env_cfg.scene.num_envs = cfg.compute.num_envs
    env_cfg.seed = cfg.seed
    return ManagerBasedRlEnv(cfg=env_cfg, device=cfg.compute.device)


@contextlib.contextmanager
def planner_timer(device: str) -> Iterator[dict[str, float]]:
    """Time every ``plan_footsteps`` call the env's ``reference`` command term makes (reward=clf
    envs replan at resets, touchdowns and step timeouts, for those envs only). Yields running
    totals ``{"calls", "envs", "s"}``; clear them with ``.update(calls=0, envs=0, s=0.0)``."""
    import march.env.reference_command as rc

    stats = {"calls": 0, "envs": 0, "s": 0.0}
    original = rc.plan_footsteps

    def timed(stance: Any, *args: Any, **kwargs: Any) -> Any:
        _sync(device)
        t0 = time.perf_counter()
        plan = original(stance, *args, **kwargs)
        _sync(device)
        stats["s"] += time.perf_counter() - t0
        stats["calls"] += 1
        stats["envs"] += int(stance.shape[0])
        return plan

    rc.plan_footsteps = timed
    try:
        yield stats
    finally:
        rc.plan_footsteps = original


def time_env_steps(
    env: Any, steps: int, warmup: int, seed: int, planner: dict[str, float] | None = None
) -> float:
    """Seconds for ``steps`` control steps after ``warmup`` untimed ones, seeded random actions.
    ``planner`` (from :func:`planner_timer`) is cleared when the timed steps begin."""
    import torch

    device = str(env.device)
    env.reset()
    gen = torch.Generator(device=device).manual_seed(seed)
    shape = (env.num_envs, env.action_manager.total_action_dim)

    def act() -> torch.Tensor:
        return 2.0 * torch.rand(shape, generator=gen, device=device) - 1.0

    with torch.no_grad():
        for _ in range(warmup):
            env.step(act())
        _sync(device)
        if planner is not None:
            planner.update(calls=0, envs=0, s=0.0)
        t0 = time.perf_counter()
        for _ in range(steps):
            env.step(act())
        _sync(device)
        return time.perf_counter() - t0


def _measure(
    build: Callable[[], Any],
    steps: int,
    warmup: int,
    seed: int,
    device: str,
    planner: dict[str, float] | None = None,
) -> tuple[float, float, int]:
    """(build seconds, timed seconds, num_envs) of one env, closed afterwards."""
    t0 = time.perf_counter()
    env = build()
    build_s = time.perf_counter() - t0
    try:
        elapsed = time_env_steps(env, steps, warmup, seed, planner)
        n = env.num_envs
    finally:
        env.close()
        del env
        _free(device)
    return build_s, elapsed, n


def bench_env(cfg: MarchConfig, steps: int, warmup: int) -> dict[str, Any]:
    from march.env.build import make_env

    device = cfg.compute.device
    builders = {
        "march_teacher": lambda: make_env(cfg, "teacher"),
        "bare_rough": lambda: bare_env(ROUGH_TASK, cfg),
        "bare_flat": lambda: bare_env(FLAT_TASK, cfg),
    }
    sps: dict[str, float] = {}
    ms: dict[str, float] = {}
    build: dict[str, float] = {}
    planner_ms = 0.0
    with stdout_to_stderr(), planner_timer(device) as planner:
        for name, make in builders.items():
            print(f"[bench] {name}: building {cfg.compute.num_envs} envs on {device}", flush=True)
            timer = planner if name == "march_teacher" else None
            build_s, elapsed, n = _measure(make, steps, warmup, cfg.seed, device, timer)
            if timer is not None:
                planner_ms = 1e3 * timer["s"] / steps
            build[name] = round(build_s, 2)
            sps[name] = n * steps / elapsed
            ms[name] = 1e3 * elapsed / steps
            print(f"[bench] {name}: {sps[name]:.1f} env steps/s", flush=True)
    return {
        "device": device,
        "num_envs": cfg.compute.num_envs,
        "steps": steps,
        "warmup": warmup,
        "torch_threads": _threads(),
        "march_teacher_steps_per_s": sps["march_teacher"],
        "bare_rough_steps_per_s": sps["bare_rough"],
        "bare_flat_steps_per_s": sps["bare_flat"],
        "ratio_march_vs_rough": sps["march_teacher"] / sps["bare_rough"],
        "ratio_march_vs_flat": sps["march_teacher"] / sps["bare_flat"],
        "ms_per_step": ms,
        "march_teacher_planner_ms_per_step": planner_ms,
        "march_teacher_planner_share": planner_ms / ms["march_teacher"],
        "build_s": build,
        "units": "steps_per_s = env steps (num_envs x control steps) per wall second; "
        "ms_per_step = one batched control step; march_teacher_planner_* = time inside the "
        "footstep planner during the march teacher's timed steps (reward=clf replans at "
        "touchdowns, step timeouts and resets)",
    }


def _threads() -> int:
    import torch

    return torch.get_num_threads()


def touchdown_rate(cfg: MarchConfig, num_courses: int = 8) -> tuple[float, float]:
    """(mean planned step duration [s], touchdowns per env per control step) of the planner's
    own walks (:func:`march.viz_plan.walk_course`) over generated courses at difficulties
    spread over [0, 1], forward command = the middle of ``env.command_vx``."""
    import numpy as np
    import torch

    from march.terrain import footholds_from_layouts, generate_course
    from march.viz_plan import walk_course

    rng = np.random.default_rng(cfg.seed)
    layouts = [generate_course(d, cfg.terrain, rng) for d in np.linspace(0, 1, num_courses)]
    footholds = footholds_from_layouts(layouts, np.stack([lay.origin for lay in layouts]))
    vx = 0.5 * (cfg.env.command_vx[0] + cfg.env.command_vx[1])
    command = torch.tensor([[vx, 0.0, 0.0]]).expand(num_courses, 3)
    walked, _ = walk_course(footholds, command, max_steps=60, seed=cfg.seed)
    durations = walked.durations[torch.isfinite(walked.durations)]
    mean_t = float(durations.mean())
    return mean_t, cfg.env.sim_dt * cfg.env.decimation / mean_t


def bench_planner_share(cfg: MarchConfig, steps: int, warmup: int) -> dict[str, Any]:
    from march.bench_planner import bench_planner
    from march.env.build import make_env
    from march.env.rewards import needs_reference

    n, device = cfg.compute.num_envs, cfg.compute.device
    result = bench_planner(n, device, steps, cfg.seed)
    with stdout_to_stderr(), planner_timer(device) as planner:
        print(f"[bench] march_teacher: building {n} envs on {device}", flush=True)
        build_s, elapsed, _ = _measure(
            lambda: make_env(cfg, "teacher"), steps, warmup, cfg.seed, device, planner
        )
    ms_env = 1e3 * elapsed / steps
    mean_t, rate = touchdown_rate(cfg)
    k = min(n, max(1, math.ceil(rate * n)))
    subset = bench_planner(k, device, steps, cfg.seed)
    in_env = needs_reference(cfg.reward)  # only the CLF teacher env runs the planner
    result.update(
        {
            "ms_per_env_step": ms_env,
            "env_build_s": round(build_s, 2),
            "planner_share_of_env_step": result["ms_per_replan_mean"] / ms_env,
            "in_env_planner_ms_per_env_step": 1e3 * planner["s"] / steps if in_env else None,
            "in_env_planner_share": 1e3 * planner["s"] / steps / ms_env if in_env else None,
            "in_env_replans_per_env_per_step": planner["envs"] / (n * steps) if in_env else None,
            "in_env_planner_calls_per_step": planner["calls"] / steps if in_env else None,
            "walk_mean_step_duration_s": mean_t,
            "walk_touchdown_rate_per_env_step": rate,
            "walk_envs_replanning_per_step": k,
            "walk_ms_per_replan_touchdown_envs": subset["ms_per_replan_mean"],
            "walk_planner_share_estimate": subset["ms_per_replan_mean"] / ms_env,
            "note": (
                "planner_share_of_env_step: one replan of all num_envs envs (synthetic courses, "
                "ms_per_replan_mean) per march teacher env step (random actions, same num_envs "
                "and device; the step already includes the env's own replans) - an upper bound. "
                "in_env_*: the planner calls the teacher env's reference command made during "
                "the timed steps (only envs at a reset, touchdown or step timeout replan; with "
                "random actions the robot falls, so resets dominate; null for reward=modelfree, "
                "which has no planner). walk_*: a walking estimate - touchdown rate = control "
                "step / mean planned step duration of the planner's own walks over generated "
                "courses, and the time of one replan of ceil(rate * num_envs) envs per step."
            ),
        }
    )
    return result


def main(argv: Sequence[str] | None = None) -> None:
    args, opts = pop_bench_options(sys.argv[1:] if argv is None else argv)
    jobs = {
        "env": lambda cfg: bench_env(cfg, opts["steps"], opts["warmup"]),
        "planner": lambda cfg: bench_planner_share(cfg, opts["steps"], opts["warmup"]),
    }
    result = run_tool(jobs, args, usage=USAGE)
    print(json.dumps(result, indent=2), flush=True)


if __name__ == "__main__":
    main()
