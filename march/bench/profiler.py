"""Where the step goes: the instrumented profile pass of ``march.bench``.

:class:`StepProfiler` wraps an env's parts (physics, managers and their terms, the footstep
planner) with timers and reports exclusive milliseconds per control step; :func:`profile_envs`
runs it over several envs in interleaved rounds; :func:`planner_timer` times only the footstep
planner calls an env makes. The sections are listed in :mod:`march.bench.env_speed`.
"""

from __future__ import annotations

import contextlib
import time
import types
from collections.abc import Callable, Iterator
from typing import Any

from march.bench.harness import Actions, chunks, sync


class StepProfiler:
    """Exclusive wall time per named section of an env step.

    :meth:`patch` replaces a method or function attribute by a timed wrapper (undone by
    :meth:`restore`). Sections nest: a section's time excludes the sections called inside it, so
    the exclusive times add up to the time of the outermost section (``step``). On CUDA every
    section boundary synchronises, so a profiled step is slower than an unprofiled one; the
    headline speed is measured without the profiler.
    """

    def __init__(self, device: str) -> None:
        self.device = str(device)
        self.self_s: dict[str, float] = {}
        self.calls: dict[str, int] = {}
        self._stack: list[list[Any]] = []
        self._undo: list[tuple[Any, str, Any, bool]] = []
        self.planner_patched = False

    def timed(self, name: str | Callable[..., str], fn: Callable[..., Any]) -> Callable[..., Any]:
        """``fn`` timed as section ``name`` (or ``name(*args, **kwargs)``)."""

        def wrapper(*args: Any, **kwargs: Any) -> Any:
            label = name(*args, **kwargs) if callable(name) else name
            sync(self.device)
            frame = [label, time.perf_counter(), 0.0]
            self._stack.append(frame)
            try:
                return fn(*args, **kwargs)
            finally:
                sync(self.device)
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
        """Wrap the env's parts (module docstring of :mod:`march.bench.env_speed` lists the
        sections)."""
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
    with torch.inference_mode():
        for name, env in envs.items():
            env.reset()
            for _ in range(opts[f"warmup_{workload}"]):
                env.step(acts[name]())
        try:
            for name, env in envs.items():
                profs[name].attach(env)
            for chunk in chunks(steps, rounds):
                for name, env in envs.items():
                    for _ in range(chunk):
                        env.step(acts[name]())
        finally:
            for prof in profs.values():
                prof.restore()
    return {name: prof.report(steps) for name, prof in profs.items()}


@contextlib.contextmanager
def planner_timer(device: str) -> Iterator[dict[str, float]]:
    """Time every ``plan_footsteps`` call the env's ``reference`` command term makes (reward=clf
    envs replan at resets, touchdowns and step timeouts, for those envs only). Yields running
    totals ``{"calls", "envs", "s"}``; clear them with ``.update(calls=0, envs=0, s=0.0)``."""
    import march.env.reference_command as rc

    stats = {"calls": 0, "envs": 0, "s": 0.0}
    original = rc.plan_footsteps

    def timed(stance: Any, *args: Any, **kwargs: Any) -> Any:
        sync(device)
        t0 = time.perf_counter()
        plan = original(stance, *args, **kwargs)
        sync(device)
        stats["s"] += time.perf_counter() - t0
        stats["calls"] += 1
        stats["envs"] += int(stance.shape[0])
        return plan

    rc.plan_footsteps = timed
    try:
        yield stats
    finally:
        rc.plan_footsteps = original
