"""``python -m march.bench <job>``: how fast march's env and planner are, as one JSON object.

    python -m march.bench env [compute.num_envs=64] [bench.steps=40] [bench.warmup_random=30]
                              [bench.warmup_standing=5]
                              [bench.profile_steps=20] [bench.rounds=8]
    python -m march.bench planner [compute.num_envs=64] [bench.steps=100]

Both jobs compose the same config as ``march.train`` (Hydra ``key=value`` overrides). The
benchmark's own options are not part of the config schema and are taken off the command line
before the config is composed: ``bench.steps`` (timed steps per env and workload),
``bench.warmup_random`` / ``bench.warmup_standing`` (untimed steps after each reset;
``bench.warmup`` sets both), ``bench.profile_steps`` (steps of the separate
instrumented pass, 0 = none) and ``bench.rounds`` (how many interleaved chunks the timed steps are
split into). Everything mjlab and warp print while building and compiling goes to stderr, so
stdout is the JSON object alone (``... | jq`` works).

``env``: on ``compute.device`` with ``compute.num_envs`` envs, three envs built side by side:
(a) the march teacher env (``make_env(cfg, "teacher")``: stepping stones, privileged
observations, paper domain randomization and, for reward=clf, the ``reference`` command term that
runs the footstep planner), (b) mjlab's bare ``Mjlab-Velocity-Rough-Unitree-G1`` and (c) bare
``Mjlab-Velocity-Flat-Unitree-G1`` (their registered configs, only ``scene.num_envs`` and
``seed`` set). Two workloads, each run on all three envs:

- ``random``: seeded random actions, uniform in [-1, 1] (one torch generator per env, seeded with
  ``cfg.seed``). Most robots fall within a second, so resets (events, DR, replans) weigh heavily.
- ``standing``: zero actions (the default pose as position target) from the spawn pose: few
  resets; the per-step cost of a robot that stays up.

Per workload: every env is reset and stepped ``warmup_<workload>`` steps (random: 30, i.e. 0.6 s,
so that robots have begun to fall; standing: 5, the zero-action G1 tilts over after 1.1-2 s, so
its timed steps end before the first falls); then the ``steps`` timed steps run
in ``rounds`` interleaved chunks (march, rough, flat, march, ...), so the ratios of one run share
the machine's load. No instrumentation is active while these are timed. Then a separate pass
(reset, the same warm-up, ``profile_steps`` steps per env, interleaved the same way) wraps the
env's parts with timers (``StepProfiler``; on CUDA each timer synchronises) and reports where the
step goes, as exclusive milliseconds per control step:
``physics`` (mujoco-warp step, forward, sensors, scene read/write), ``actions``, ``commands``
(``commands/planner``: the footstep planner), ``rewards``, ``observations``, ``terminations``,
``events`` (interval pushes and the reset-time DR terms), ``resets`` (the rest of mjlab's
``_reset_idx``: sim and scene reset, manager resets), ``curriculum`` and ``other`` (mjlab's
glue in ``step``). ``sections_ms`` lists the finer sections (each reward, observation, termination,
command and event term) largest first.

``planner``: :func:`march.bench.planner_speed.bench_planner` (``steps`` timed replans of all
``num_envs`` envs on synthetic courses), plus the march teacher env's step time measured in the
same run: ``planner_share_of_env_step`` = ms per full-batch replan / ms per env step (an upper
bound: the env plans its reset envs plus one fixed batch of 1/8 of the envs per step). ``in_env_*`` measures the
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
import types
from collections.abc import Callable, Iterator, Sequence
from typing import Any

from march.config import MarchConfig
from march.config.cli import fail, run_tool

USAGE = (
    "usage: python -m march.bench env|planner [compute.num_envs=64] [compute.device=...] "
    "[bench.steps=N] [bench.warmup=N] [bench.warmup_random=N] [bench.warmup_standing=N] "
    "[bench.profile_steps=N] [bench.rounds=N] [key=value ...]"
)
JOB_DEFAULTS: dict[str, dict[str, int]] = {
    "env": {
        "steps": 40,
        "warmup_random": 30,
        "warmup_standing": 5,
        "profile_steps": 20,
        "rounds": 8,
    },
    "planner": {"steps": 100, "warmup": 10, "profile_steps": 0, "rounds": 1},
}
"""Per job: timed steps (env: per env and workload), untimed warm-up steps after each reset,
steps of the instrumented profile pass (env only; 0 = none) and interleaved chunks. Sized for a
loaded 2-core machine at 64 envs (about 10 minutes)."""
BENCH_MINIMUM = {
    "steps": 1,
    "warmup": 0,
    "warmup_random": 0,
    "warmup_standing": 0,
    "profile_steps": 0,
    "rounds": 1,
}
"""Smallest value of each option; ``bench.warmup=N`` sets both workloads' warm-up."""
ROUGH_TASK = "Mjlab-Velocity-Rough-Unitree-G1"
FLAT_TASK = "Mjlab-Velocity-Flat-Unitree-G1"
ENV_NAMES = ("march_teacher", "bare_rough", "bare_flat")
WORKLOADS = ("random", "standing")
"""``random``: seeded uniform actions in [-1, 1]; ``standing``: zero actions (default pose)."""


def pop_bench_options(argv: Sequence[str]) -> tuple[list[str], dict[str, int]]:
    """Split ``bench.<option>=N`` off the overrides (they are not config keys); returns the
    remaining overrides and the options given (job defaults: :data:`JOB_DEFAULTS`)."""
    rest: list[str] = []
    opts: dict[str, int] = {}
    for arg in argv:
        if not arg.startswith("bench."):
            rest.append(arg)
            continue
        key, _, value = arg[len("bench.") :].partition("=")
        if key not in BENCH_MINIMUM:
            known = ", ".join(f"bench.{k}=N" for k in BENCH_MINIMUM)
            fail(f"unknown benchmark option {arg!r}; use {known}")
        try:
            n = int(value)
        except ValueError:
            fail(f"{arg}: expected an integer")
        if n < BENCH_MINIMUM[key]:
            fail(f"{arg}: bench.{key} must be >= {BENCH_MINIMUM[key]}")
        opts[key] = n
    return rest, opts


def job_options(job: str, given: dict[str, int]) -> dict[str, int]:
    """The job's defaults with the given options over them (``bench.warmup=N``: the warm-up of
    both env workloads, unless one is given by itself)."""
    opts = {**JOB_DEFAULTS.get(job, JOB_DEFAULTS["env"]), **given}
    if "warmup" in given:
        for w in WORKLOADS:
            opts[f"warmup_{w}"] = given.get(f"warmup_{w}", given["warmup"])
    return opts


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
    act = Actions(env, "random", seed)
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


class Actions:
    """The actions of one workload for one env: ``random`` (seeded uniform in [-1, 1], its own
    generator) or ``standing`` (zeros: the default pose as position target)."""

    def __init__(self, env: Any, workload: str, seed: int) -> None:
        import torch

        if workload not in WORKLOADS:
            raise ValueError(f"workload {workload!r}: use one of {WORKLOADS}")
        self.device = str(env.device)
        self.shape = (env.num_envs, env.action_manager.total_action_dim)
        self.random = workload == "random"
        self.gen = torch.Generator(device=self.device).manual_seed(seed)
        self.zeros = torch.zeros(self.shape, device=self.device)

    def __call__(self) -> Any:
        import torch

        if self.random:
            return 2.0 * torch.rand(self.shape, generator=self.gen, device=self.device) - 1.0
        return self.zeros


# --------------------------------------------------------------------------------------------
# Where the step goes.


class StepProfiler:
    """Exclusive wall time per named section of an env step.

    :meth:`patch` replaces a method or function attribute by a timed wrapper (undone by
    :meth:`restore`). Sections nest: a section's time excludes the sections called inside it, so
    the exclusive times add up to the time of the outermost section (``step``). On CUDA every
    section boundary synchronises, so a profiled step is slower than an unprofiled one; the
    headline speed is measured without the profiler.
    """

    def __init__(self, device: str) -> None:
        self.cuda = str(device).startswith("cuda")
        self.self_s: dict[str, float] = {}
        self.calls: dict[str, int] = {}
        self._stack: list[list[Any]] = []
        self._undo: list[tuple[Any, str, Any, bool]] = []
        self.planner_patched = False

    def _sync(self) -> None:
        if self.cuda:
            import torch

            torch.cuda.synchronize()

    def timed(self, name: str | Callable[..., str], fn: Callable[..., Any]) -> Callable[..., Any]:
        """``fn`` timed as section ``name`` (or ``name(*args, **kwargs)``)."""

        def wrapper(*args: Any, **kwargs: Any) -> Any:
            label = name(*args, **kwargs) if callable(name) else name
            self._sync()
            frame = [label, time.perf_counter(), 0.0]
            self._stack.append(frame)
            try:
                return fn(*args, **kwargs)
            finally:
                self._sync()
                elapsed = time.perf_counter() - frame[1]
                self._stack.pop()
                self.self_s[label] = self.self_s.get(label, 0.0) + elapsed - frame[2]
                self.calls[label] = self.calls.get(label, 0) + 1
                if self._stack:
                    self._stack[-1][2] += elapsed

        return wrapper

    def patch(self, obj: Any, attr: str, name: str | Callable[..., str]) -> None:
        original = getattr(obj, attr)
        own = attr in getattr(obj, "__dict__", {})
        setattr(obj, attr, self.timed(name, original))
        self._undo.append((obj, attr, original, own))

    def restore(self) -> None:
        for obj, attr, original, own in reversed(self._undo):
            if own:
                setattr(obj, attr, original)
            else:
                delattr(obj, attr)
        self._undo.clear()

    def reset(self) -> None:
        self.self_s.clear()
        self.calls.clear()

    def attach(self, env: Any) -> None:
        """Wrap the env's parts (module docstring of :mod:`march.bench` lists the sections)."""
        import march.env.reference_command as rc
        from march.env.rewards import REFERENCE_COMMAND

        p = self.patch
        p(env, "step", "other")
        p(env, "_reset_idx", "resets")
        p(env.sim, "step", "physics/step")
        p(env.sim, "forward", "physics/forward")
        p(env.sim, "sense", "physics/sense")
        p(env.sim, "reset", "resets/sim")
        p(env.scene, "update", "physics/scene_update")
        p(env.scene, "write_data_to_sim", "physics/write")
        p(env.scene, "reset", "resets/scene")
        am = env.action_manager
        for attr in ("process_action", "apply_action", "reset"):
            p(am, attr, f"actions/{attr}")
        for mgr, cat in (
            (env.termination_manager, "terminations"),
            (env.reward_manager, "rewards"),
        ):
            p(mgr, "compute", cat)
            p(mgr, "reset", f"{cat}/reset")
            for name, term in zip(mgr._term_names, mgr._term_cfgs, strict=True):
                self._patch_term(term, f"{cat}/{name}")
        om = env.observation_manager
        p(om, "compute", "observations")
        p(om, "reset", "observations/reset")
        for group, names in om._group_obs_term_names.items():
            for name, term in zip(names, om._group_obs_term_cfgs[group], strict=True):
                self._patch_term(term, f"observations/{group}/{name}")
        em = env.event_manager
        p(em, "apply", lambda mode, *a, **k: f"events/{mode}")
        p(em, "reset", "events/reset")
        for mode, names in em._mode_term_names.items():
            for name, term in zip(names, em._mode_term_cfgs[mode], strict=True):
                self._patch_term(term, f"events/{mode}/{name}")
        cm = env.command_manager
        p(cm, "compute", "commands")
        p(cm, "reset", "commands/reset")
        for name, term in getattr(cm, "_terms", {}).items():
            p(term, "compute", f"commands/{name}")
        if REFERENCE_COMMAND in getattr(cm, "_terms", {}) and hasattr(rc, "plan_footsteps"):
            p(rc, "plan_footsteps", "commands/planner")
            self.planner_patched = True
        p(env.curriculum_manager, "compute", "curriculum")
        p(env.metrics_manager, "compute", "other/metrics")
        p(env.metrics_manager, "compute_substep", "other/metrics")

    def _patch_term(self, term_cfg: Any, name: str) -> None:
        # Class-based terms (ManagerTermBase instances) keep their own reset(); only plain
        # functions are wrapped, the others count towards their manager.
        if isinstance(term_cfg.func, types.FunctionType):
            self.patch(term_cfg, "func", name)

    def report(self, steps: int) -> dict[str, Any]:
        """ms per control step by category and by section (largest first), and call counts."""
        ms = {k: 1e3 * v / steps for k, v in self.self_s.items()}
        cats: dict[str, float] = {}
        for k, v in ms.items():
            cat = k.split("/", 1)[0]
            cats[cat] = cats.get(cat, 0.0) + v
        total = sum(cats.values())
        order = sorted(cats, key=lambda c: -cats[c])
        planner_ms = ms.get("commands/planner", 0.0) if self.planner_patched else None
        planner_calls = self.calls.get("commands/planner", 0)
        return {
            "profiled_ms_per_step": total,
            "categories_ms": {c: round(cats[c], 3) for c in order},
            "categories_share": {c: round(cats[c] / total, 4) for c in order} if total else {},
            "sections_ms": {
                k: round(v, 3) for k, v in sorted(ms.items(), key=lambda kv: -kv[1]) if v >= 1e-3
            },
            "planner_ms_per_step": planner_ms,
            "planner_calls_per_step": planner_calls / steps if planner_ms is not None else None,
            "planner_ms_per_call": (
                1e3 * self.self_s["commands/planner"] / planner_calls if planner_calls else None
            ),
        }


def profile_envs(
    envs: dict[str, Any], workload: str, opts: dict[str, int], seed: int
) -> dict[str, dict[str, Any]]:
    """:class:`StepProfiler` reports of ``profile_steps`` steps of ``workload`` per env, after a
    reset and ``warmup`` unprofiled steps, in the same interleaved rounds as the timed steps (so
    the profiles of one run share the machine's load and compare across envs)."""
    import torch

    steps, rounds = opts["profile_steps"], min(opts["rounds"], opts["profile_steps"])
    acts = {name: Actions(env, workload, seed) for name, env in envs.items()}
    profs = {name: StepProfiler(str(env.device)) for name, env in envs.items()}
    with torch.no_grad():
        for name, env in envs.items():
            env.reset()
            for _ in range(opts[f"warmup_{workload}"]):
                env.step(acts[name]())
        try:
            for name, env in envs.items():
                profs[name].attach(env)
            for chunk in _chunks(steps, rounds):
                for name, env in envs.items():
                    for _ in range(chunk):
                        env.step(acts[name]())
        finally:
            for prof in profs.values():
                prof.restore()
    return {name: prof.report(steps) for name, prof in profs.items()}


def _chunks(steps: int, rounds: int) -> list[int]:
    """``steps`` split into ``rounds`` near-equal chunks."""
    return [steps // rounds + (1 if r < steps % rounds else 0) for r in range(rounds)]


def run_workload(
    envs: dict[str, Any], workload: str, opts: dict[str, int], seed: int, device: str
) -> dict[str, Any]:
    """Headline speed (interleaved rounds, no instrumentation) and profile of one workload."""
    import torch

    steps, rounds = opts["steps"], min(opts["rounds"], opts["steps"])
    warmup = opts[f"warmup_{workload}"]
    acts = {name: Actions(env, workload, seed) for name, env in envs.items()}
    resets = {name: torch.zeros((), device=device) for name in envs}
    elapsed = dict.fromkeys(envs, 0.0)
    with torch.no_grad():
        for name, env in envs.items():
            env.reset()
            for _ in range(warmup):
                env.step(acts[name]())
        for chunk in _chunks(steps, rounds):
            for name, env in envs.items():
                _sync(device)
                t0 = time.perf_counter()
                for _ in range(chunk):
                    env.step(acts[name]())
                    resets[name] += env.reset_buf.sum()  # on device: no sync in the loop
                _sync(device)
                elapsed[name] += time.perf_counter() - t0
    sps = {name: env.num_envs * steps / elapsed[name] for name, env in envs.items()}
    out: dict[str, Any] = {
        "steps_per_s": sps,
        "ms_per_step": {name: 1e3 * elapsed[name] / steps for name in envs},
        "resets_per_env_step": {
            name: float(resets[name]) / (env.num_envs * steps) for name, env in envs.items()
        },
        "ratio_march_vs_rough": sps["march_teacher"] / sps["bare_rough"],
        "ratio_march_vs_flat": sps["march_teacher"] / sps["bare_flat"],
    }
    if opts["profile_steps"] > 0:
        out["profile"] = profile_envs(envs, workload, opts, seed)
        for name, prof in out["profile"].items():
            top = ", ".join(f"{c} {v:.1f}" for c, v in prof["categories_ms"].items())
            print(f"[bench] {workload} profile {name} (ms/step): {top}", flush=True)
        march = out["profile"]["march_teacher"]
        if march["planner_ms_per_step"] is not None:
            march["planner_share"] = march["planner_ms_per_step"] / march["profiled_ms_per_step"]
    return out


def bench_env(cfg: MarchConfig, opts: dict[str, int]) -> dict[str, Any]:
    from march.env.build import make_env

    device = cfg.compute.device
    builders = {
        "march_teacher": lambda: make_env(cfg, "teacher"),
        "bare_rough": lambda: bare_env(ROUGH_TASK, cfg),
        "bare_flat": lambda: bare_env(FLAT_TASK, cfg),
    }
    envs: dict[str, Any] = {}
    build: dict[str, float] = {}
    results: dict[str, Any] = {}
    try:
        with stdout_to_stderr():
            for name, make in builders.items():
                print(
                    f"[bench] {name}: building {cfg.compute.num_envs} envs on {device}", flush=True
                )
                t0 = time.perf_counter()
                envs[name] = make()
                build[name] = round(time.perf_counter() - t0, 2)
            for workload in WORKLOADS:
                results[workload] = run_workload(envs, workload, opts, cfg.seed, device)
                sps = results[workload]["steps_per_s"]
                print(
                    f"[bench] {workload}: "
                    + ", ".join(f"{n} {v:.1f}" for n, v in sps.items())
                    + f" env steps/s; march/rough {results[workload]['ratio_march_vs_rough']:.2f}",
                    flush=True,
                )
    finally:
        for env in envs.values():
            env.close()
        envs.clear()
        _free(device)
    rnd = results["random"]
    march_profile = rnd.get("profile", {}).get("march_teacher", {})
    return {
        "device": device,
        "num_envs": cfg.compute.num_envs,
        "steps": opts["steps"],
        "warmup": {w: opts[f"warmup_{w}"] for w in WORKLOADS},
        "profile_steps": opts["profile_steps"],
        "rounds": opts["rounds"],
        "torch_threads": _threads(),
        "reward": cfg.reward.name,
        "dr": cfg.dr.name,
        # The random workload's numbers at the top level (the keys of earlier versions).
        "march_teacher_steps_per_s": rnd["steps_per_s"]["march_teacher"],
        "bare_rough_steps_per_s": rnd["steps_per_s"]["bare_rough"],
        "bare_flat_steps_per_s": rnd["steps_per_s"]["bare_flat"],
        "ratio_march_vs_rough": rnd["ratio_march_vs_rough"],
        "ratio_march_vs_flat": rnd["ratio_march_vs_flat"],
        "ms_per_step": rnd["ms_per_step"],
        "march_teacher_planner_ms_per_step": march_profile.get("planner_ms_per_step"),
        "march_teacher_planner_share": march_profile.get("planner_share"),
        "ratio_march_vs_rough_by_workload": {
            w: results[w]["ratio_march_vs_rough"] for w in WORKLOADS
        },
        "min_ratio_march_vs_rough": min(results[w]["ratio_march_vs_rough"] for w in WORKLOADS),
        "workloads": results,
        "build_s": build,
        "units": "steps_per_s = env steps (num_envs x control steps) per wall second, timed "
        "without instrumentation in interleaved rounds; ms_per_step = one batched control step; "
        "profile.*_ms = exclusive ms per control step in a separate instrumented pass "
        "(categories: physics, actions, commands incl. commands/planner, rewards, observations, "
        "terminations, events, resets, curriculum, other = mjlab glue); march_teacher_planner_* "
        "= the footstep planner's time in that pass (random workload); resets_per_env_step = "
        "episode ends per env and control step",
    }


def _threads() -> int:
    import torch

    return torch.get_num_threads()


def touchdown_rate(cfg: MarchConfig, num_courses: int = 8) -> tuple[float, float]:
    """(mean planned step duration [s], touchdowns per env per control step) of the planner's
    own walks (:func:`march.viz.plan_view.walk_course`) over generated courses at difficulties
    spread over [0, 1], forward command = the middle of ``env.command_vx``."""
    import numpy as np
    import torch

    from march.viz.plan_view import walk_course
    from march.world.courses import footholds_from_layouts, generate_course

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
    from march.bench.planner_speed import bench_planner
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
    args, given = pop_bench_options(sys.argv[1:] if argv is None else argv)
    job = args[0] if args else ""
    opts = job_options(job, given)
    jobs = {
        "env": lambda cfg: bench_env(cfg, opts),
        "planner": lambda cfg: bench_planner_share(cfg, opts["steps"], opts["warmup"]),
    }
    result = run_tool(jobs, args, usage=USAGE)
    print(json.dumps(result, indent=2), flush=True)
