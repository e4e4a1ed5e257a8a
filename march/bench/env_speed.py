"""``python -m march.bench env``: how fast the march teacher env steps against bare mjlab, as JSON.

On ``compute.device`` with ``compute.num_envs`` envs, three envs built side by side:
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

The JSON's ``targets`` judges the headline ratios against the step's speed targets
(:mod:`march.bench.targets`), and the run ends with one ``[bench] target ...`` line each.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

from march.bench.harness import WORKLOADS, Actions, chunks, free, stdout_to_stderr, sync
from march.bench.ops import count_ops
from march.bench.profiler import profile_envs
from march.bench.targets import judge, verdict_lines
from march.config import MarchConfig

ROUGH_TASK = "Mjlab-Velocity-Rough-Unitree-G1"
FLAT_TASK = "Mjlab-Velocity-Flat-Unitree-G1"
ENV_NAMES = ("march_teacher", "bare_rough", "bare_flat")


def run_workload(
    envs: dict[str, Any], workload: str, opts: dict[str, Any], seed: int, device: str
) -> dict[str, Any]:
    """Headline speed (interleaved rounds over thread counts and envs, no instrumentation),
    compute ops per step and the profile of one workload."""
    import torch

    steps, rounds = opts["steps"], min(opts["rounds"], opts["steps"])
    threads = list(opts.get("threads") or [torch.get_num_threads()])
    warmup = opts[f"warmup_{workload}"]
    acts = {name: Actions(env, workload, seed) for name, env in envs.items()}
    resets = {name: torch.zeros((), device=device) for name in envs}
    elapsed = {t: dict.fromkeys(envs, 0.0) for t in threads}
    with torch.inference_mode():
        for name, env in envs.items():
            env.reset()
            for _ in range(warmup):
                env.step(acts[name]())
        if opts.get("compiled") and len(threads) > 1:
            # inductor's CPU code is guarded on the thread count: compile for each count here,
            # not in a timed round
            for t in threads:
                torch.set_num_threads(t)
                for name, env in envs.items():
                    env.step(acts[name]())
        for chunk in chunks(steps, rounds):
            for t in threads:
                torch.set_num_threads(t)
                for name, env in envs.items():
                    sync(device)
                    t0 = time.perf_counter()
                    for _ in range(chunk):
                        env.step(acts[name]())
                        resets[name] += env.reset_buf.sum()  # on device: no sync in the loop
                    sync(device)
                    elapsed[t][name] += time.perf_counter() - t0
    by_threads: dict[str, Any] = {}
    for t in threads:
        sps = {name: env.num_envs * steps / elapsed[t][name] for name, env in envs.items()}
        by_threads[str(t)] = {
            "steps_per_s": sps,
            "ms_per_step": {name: 1e3 * elapsed[t][name] / steps for name in envs},
            "ratio_march_vs_rough": sps["march_teacher"] / sps["bare_rough"],
        }
        if "bare_flat" in sps:
            by_threads[str(t)]["ratio_march_vs_flat"] = sps["march_teacher"] / sps["bare_flat"]
    for t, b in by_threads.items():  # printed the moment it is measured (the GPU check's log)
        print(
            f"[bench] {workload}, {t} thread(s): "
            + ", ".join(f"{n} {v:.1f}" for n, v in b["steps_per_s"].items())
            + f" env steps/s; march/rough {b['ratio_march_vs_rough']:.2f}",
            file=sys.stderr,
            flush=True,
        )
    first = by_threads[str(threads[0])]
    out: dict[str, Any] = {
        **first,
        "resets_per_env_step": {
            name: float(resets[name]) / (env.num_envs * steps * len(threads))
            for name, env in envs.items()
        },
        "by_threads": by_threads,
    }
    torch.set_num_threads(threads[0])
    if opts["op_steps"] > 0:
        counted = {
            name: count_ops(env, workload, opts["op_steps"], warmup, seed)
            for name, env in envs.items()
        }
        out["ops_per_step"] = {name: c["ops_per_step"] for name, c in counted.items()}
        out["top_ops"] = {name: c["top_ops"] for name, c in counted.items()}
        out["ratio_ops_march_vs_rough"] = (
            out["ops_per_step"]["march_teacher"] / out["ops_per_step"]["bare_rough"]
        )
        # The CUDA code path's count: on a GPU the count above is that path's. On a CPU it is
        # the same number, because march's step has one code path on both devices since issue
        # 41 (the planner's fused scoring was the only device-dependent branch; decisions.md
        # "One planner path"), so it is not counted twice.
        cuda_path = out["ops_per_step"]["march_teacher"]
        out["ops_per_step_cuda_path"] = dict(out["ops_per_step"])
        out["ratio_ops_march_vs_rough_cuda_path"] = out["ratio_ops_march_vs_rough"]
        print(
            f"[bench] {workload} compute ops per step: "
            + ", ".join(f"{n} {v:.0f}" for n, v in out["ops_per_step"].items())
            + f"; march/rough {out['ratio_ops_march_vs_rough']:.2f}"
            + f" (CUDA code path: the same code, march {cuda_path:.0f})",
            flush=True,
        )
    if opts["profile_steps"] > 0:
        for t in threads:
            torch.set_num_threads(t)
            profile = profile_envs(envs, workload, opts, seed)
            nonphys = {
                name: prof["profiled_ms_per_step"] - prof["categories_ms"].get("physics", 0.0)
                for name, prof in profile.items()
            }
            by_threads[str(t)]["profile"] = profile
            by_threads[str(t)]["nonphysics_ms_per_step"] = nonphys
            by_threads[str(t)]["ratio_nonphysics_march_vs_rough"] = (
                nonphys["march_teacher"] / nonphys["bare_rough"]
            )
            for name, prof in profile.items():
                top = ", ".join(f"{c} {v:.1f}" for c, v in prof["categories_ms"].items())
                print(f"[bench] {workload} {t} thr profile {name} (ms/step): {top}", flush=True)
            march = profile["march_teacher"]
            if march["planner_ms_per_step"] is not None:
                march["planner_share"] = (
                    march["planner_ms_per_step"] / march["profiled_ms_per_step"]
                )
        torch.set_num_threads(threads[0])
        for key in ("profile", "nonphysics_ms_per_step", "ratio_nonphysics_march_vs_rough"):
            out[key] = first[key]
        out["worst_ratio_nonphysics_march_vs_rough"] = max(
            b["ratio_nonphysics_march_vs_rough"] for b in by_threads.values()
        )
    return out


def bench_env(cfg: MarchConfig, opts: dict[str, Any]) -> dict[str, Any]:
    import torch

    from march.compiled_math import compile_report
    from march.env.build import bare_env, make_env

    device = cfg.compute.device
    n, seed = cfg.compute.num_envs, cfg.seed
    if not opts.get("threads"):
        on_gpu = device.startswith("cuda")
        opts = {**opts, "threads": [torch.get_num_threads()] if on_gpu else [1, 2]}
    opts = {**opts, "compiled": cfg.compute.compile_math}
    builders = {
        "march_teacher": lambda: make_env(cfg, "teacher"),
        "bare_rough": lambda: bare_env(ROUGH_TASK, n, seed, device),
        "bare_flat": lambda: bare_env(FLAT_TASK, n, seed, device),
    }
    builders = {k: builders[k] for k in opts.get("envs") or ENV_NAMES}
    workloads = list(opts.get("workloads") or WORKLOADS)
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
            for workload in workloads:
                results[workload] = run_workload(envs, workload, opts, cfg.seed, device)
                if opts.get("partial"):
                    _write_partial(Path(opts["partial"]), cfg, build, results, workloads)
    finally:
        for env in envs.values():
            env.close()
        envs.clear()
        free(device)
    rnd = results[workloads[0]]
    march_profile = rnd.get("profile", {}).get("march_teacher", {})
    compiled = compile_report() if cfg.compute.compile_math else None
    if compiled is not None:
        per_fn = ", ".join(f"{f} {s:.0f} s" for f, s in compiled["seconds"].items())
        print(
            f"[bench] compile_math: {sum(compiled['graphs'].values())} graphs compiled in "
            f"{compiled['total_s']:.0f} s ({per_fn}); recompiles {compiled['recompiles']}",
            file=sys.stderr,
            flush=True,
        )
    report = {
        "device": device,
        "num_envs": cfg.compute.num_envs,
        "steps": opts["steps"],
        "workload_names": workloads,
        "env_names": list(builders),
        "warmup": {w: opts[f"warmup_{w}"] for w in workloads},
        "profile_steps": opts["profile_steps"],
        "rounds": opts["rounds"],
        "torch_threads": _threads(),
        "threads": [int(t) for t in rnd["by_threads"]],
        "reward": cfg.reward.name,
        "dr": cfg.dr.name,
        # The first workload's numbers (random unless bench.workloads says otherwise) at the
        # top level (the keys of earlier versions; flat's only where it was benched).
        "march_teacher_steps_per_s": rnd["steps_per_s"]["march_teacher"],
        "bare_rough_steps_per_s": rnd["steps_per_s"]["bare_rough"],
        "bare_flat_steps_per_s": rnd["steps_per_s"].get("bare_flat"),
        "ratio_march_vs_rough": rnd["ratio_march_vs_rough"],
        "ratio_march_vs_flat": rnd.get("ratio_march_vs_flat"),
        "ms_per_step": rnd["ms_per_step"],
        "march_teacher_planner_ms_per_step": march_profile.get("planner_ms_per_step"),
        "march_teacher_planner_share": march_profile.get("planner_share"),
        "ratio_march_vs_rough_by_threads": {
            t: {w: results[w]["by_threads"][t]["ratio_march_vs_rough"] for w in workloads}
            for t in rnd["by_threads"]
        },
        **_headline(results),
        "workloads": results,
        "build_s": build,
        "compile": compiled,
        "units": "steps_per_s = env steps (num_envs x control steps) per wall second, timed "
        "without instrumentation in interleaved rounds; ms_per_step = one batched control step; "
        "profile.*_ms = exclusive ms per control step in a separate instrumented pass "
        "(categories: physics, actions, commands incl. commands/planner, rewards, observations, "
        "terminations, events, resets, curriculum, other = mjlab glue); march_teacher_planner_* "
        "= the footstep planner's time in that pass (random workload); resets_per_env_step = "
        "episode ends per env and control step; compile (compute.compile_math only) = graphs and "
        "wall seconds of the calls that compiled, per compiled function, and recompiles (graphs "
        "beyond one per function)",
    }
    for line in verdict_lines(report["targets"], "[bench]"):
        print(line, file=sys.stderr, flush=True)
    return report


def _headline(results: dict[str, Any]) -> dict[str, Any]:
    """March / bare rough's speed ratio per workload; ops and non-physics time per step by
    workload and env, and march / bare rough's worst (largest) ratio over the workloads in
    ``results`` (and thread counts, for the time)."""
    done = list(results)
    out: dict[str, Any] = {
        "ratio_march_vs_rough_by_workload": {w: results[w]["ratio_march_vs_rough"] for w in done}
    }
    if done:
        out["min_ratio_march_vs_rough"] = min(
            b["ratio_march_vs_rough"] for w in done for b in results[w]["by_threads"].values()
        )
    if done and all("ops_per_step" in results[w] for w in done):
        out["ops_per_step"] = {w: results[w]["ops_per_step"] for w in done}
        out["ratio_ops_march_vs_rough"] = max(results[w]["ratio_ops_march_vs_rough"] for w in done)
        cuda = [results[w].get("ratio_ops_march_vs_rough_cuda_path") for w in done]
        if all(c is not None for c in cuda):  # the CUDA code path's, counted on a CPU
            out["ratio_ops_march_vs_rough_cuda_path"] = max(cuda)
    if done and all("nonphysics_ms_per_step" in results[w] for w in done):
        out["nonphysics_ms_per_step"] = {w: results[w]["nonphysics_ms_per_step"] for w in done}
        out["nonphysics_ms_per_step_by_threads"] = {
            w: {t: b["nonphysics_ms_per_step"] for t, b in results[w]["by_threads"].items()}
            for w in done
        }
        out["ratio_nonphysics_march_vs_rough"] = max(
            results[w]["worst_ratio_nonphysics_march_vs_rough"] for w in done
        )
    out["targets"] = judge(out)
    return out


def _write_partial(
    path: Path,
    cfg: MarchConfig,
    build: dict[str, float],
    results: dict[str, Any],
    workloads: list[str],
) -> None:
    """``bench.partial``: what the finished workloads measured, under the final JSON's keys
    (atomic, rewritten after each workload), for a run that a time limit may stop."""
    from march.compiled_math import compile_report
    from march.store.checkpoint import write_json_atomic
    from march.strict_json import strict

    write_json_atomic(
        strict(
            {
                "partial": len(results) < len(workloads),
                "completed_workloads": list(results),
                "device": cfg.compute.device,
                "num_envs": cfg.compute.num_envs,
                "build_s": build,
                **_headline(results),
                "workloads": results,
                "compile": compile_report() if cfg.compute.compile_math else None,
            }
        ),
        path,
    )


def _threads() -> int:
    import torch

    return torch.get_num_threads()
