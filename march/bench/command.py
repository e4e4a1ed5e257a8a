"""``python -m march.bench <job>``: how fast march's env and planner are, as one JSON object.

    python -m march.bench env [compute.num_envs=64] [bench.steps=40] [bench.warmup_random=30]
                              [bench.warmup_standing=5]
                              [bench.profile_steps=20] [bench.op_steps=10] [bench.rounds=8]
                              [bench.threads=1,2] [bench.partial=FILE]
                              [bench.workloads=random,standing]
                              [bench.envs=march_teacher,bare_rough,bare_flat]
    python -m march.bench planner [compute.num_envs=64] [bench.steps=100]

Both jobs compose the same config as ``march.train`` (Hydra ``key=value`` overrides). The
benchmark's own options are not part of the config schema and are taken off the command line
before the config is composed: ``bench.steps`` (timed steps per env and workload),
``bench.warmup_random`` / ``bench.warmup_standing`` (untimed steps after each reset;
``bench.warmup`` sets both), ``bench.profile_steps`` (steps of the separate
instrumented pass, 0 = none) and ``bench.rounds`` (how many interleaved chunks the timed steps are
split into); ``bench.partial=FILE`` (:data:`PATH_OPTIONS`); ``bench.workloads`` and
``bench.envs`` (:data:`NAME_OPTIONS`: which workloads and envs, in that order; the GPU check times
only march and bare rough on the random workload). Everything mjlab and warp print
while building and compiling goes to stderr, so stdout is the JSON object alone (``... | jq``
works).

What each job measures and the keys of its JSON object: :mod:`march.bench.env_speed` (``env``)
and :mod:`march.bench.planner_speed` (``planner``).
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from typing import Any

from march import strict_json
from march.bench.env_speed import bench_env
from march.bench.harness import WORKLOADS
from march.bench.planner_speed import bench_planner_share
from march.config.cli import fail, run_tool

USAGE = (
    "usage: python -m march.bench env|planner [compute.num_envs=64] [compute.device=...] "
    "[bench.steps=N] [bench.warmup=N] [bench.warmup_random=N] [bench.warmup_standing=N] "
    "[bench.profile_steps=N] [bench.op_steps=N] [bench.rounds=N] [bench.threads=1,2] "
    "[bench.partial=FILE] [bench.workloads=random,standing] "
    "[bench.envs=march_teacher,bare_rough,bare_flat] [key=value ...]"
)
JOB_DEFAULTS: dict[str, dict[str, int]] = {
    "env": {
        "steps": 40,
        "warmup_random": 30,
        "warmup_standing": 5,
        "profile_steps": 20,
        "op_steps": 10,
        "rounds": 8,
    },
    "planner": {"steps": 100, "warmup": 10, "profile_steps": 0, "op_steps": 0, "rounds": 1},
}
"""Per job: timed steps (env: per env and workload), untimed warm-up steps after each reset,
steps of the instrumented profile pass (env only; 0 = none), steps of the op-counting pass (env
only; 0 = none) and interleaved chunks. ``bench.threads=1,2`` (env only) times every listed torch
thread count in the same interleaved rounds (default on CPU: 1 and 2, whatever
``compute.torch_threads`` says; on CUDA the current count). Sized for a
loaded 2-core machine at 64 envs (about 10 minutes)."""
BENCH_MINIMUM = {
    "steps": 1,
    "warmup": 0,
    "warmup_random": 0,
    "warmup_standing": 0,
    "profile_steps": 0,
    "op_steps": 0,
    "rounds": 1,
    "threads": 1,
}
"""Smallest value of each option; ``bench.warmup=N`` sets both workloads' warm-up."""
PATH_OPTIONS = ("partial",)
"""Options that name a file: ``bench.partial=FILE`` (env job) rewrites FILE, atomically, after
each workload with what has been measured so far (``partial``, ``completed_workloads``), so that
a run stopped by a time limit keeps its finished workloads (the GPU check reads it)."""


NAME_OPTIONS = {
    "workloads": WORKLOADS,
    "envs": ("march_teacher", "bare_rough", "bare_flat"),
}
"""Options that pick names (comma-separated, in the given order, no repeats): the workloads run
and the envs built; ``march_teacher`` and ``bare_rough`` are always among the envs (every
headline ratio is march / bare rough)."""


def _names(arg: str, key: str, value: str) -> list[str]:
    names = [v for v in value.split(",") if v]
    allowed = NAME_OPTIONS[key]
    bad = [v for v in names if v not in allowed]
    if not names or bad or len(set(names)) != len(names):
        fail(f"{arg}: expected distinct names from {', '.join(allowed)}")
    if key == "envs" and not {"march_teacher", "bare_rough"} <= set(names):
        fail(f"{arg}: march_teacher and bare_rough are always benched (ratios are march / rough)")
    return names


def pop_bench_options(argv: Sequence[str]) -> tuple[list[str], dict[str, Any]]:
    """Split ``bench.<option>=N`` off the overrides (they are not config keys); returns the
    remaining overrides and the options given (job defaults: :data:`JOB_DEFAULTS`)."""
    rest: list[str] = []
    opts: dict[str, Any] = {}
    for arg in argv:
        if not arg.startswith("bench."):
            rest.append(arg)
            continue
        key, _, value = arg[len("bench.") :].partition("=")
        if key in PATH_OPTIONS:
            if not value:
                fail(f"{arg}: expected a file path")
            opts[key] = value
            continue
        if key in NAME_OPTIONS:
            opts[key] = _names(arg, key, value)
            continue
        if key not in BENCH_MINIMUM:
            known = ", ".join(
                [f"bench.{k}=N" for k in BENCH_MINIMUM]
                + ["bench.partial=FILE", "bench.workloads=a,b", "bench.envs=a,b"]
            )
            fail(f"unknown benchmark option {arg!r}; use {known}")
        try:
            ns = [int(v) for v in value.split(",")] if key == "threads" else [int(value)]
        except ValueError:
            fail(f"{arg}: expected an integer" + (" list (1,2)" if key == "threads" else ""))
        if min(ns) < BENCH_MINIMUM[key]:
            fail(f"{arg}: bench.{key} must be >= {BENCH_MINIMUM[key]}")
        opts[key] = ns if key == "threads" else ns[0]
    return rest, opts


def job_options(job: str, given: dict[str, Any]) -> dict[str, Any]:
    """The job's defaults with the given options over them (``bench.warmup=N``: the warm-up of
    both env workloads, unless one is given by itself)."""
    opts = {**JOB_DEFAULTS.get(job, JOB_DEFAULTS["env"]), **given}
    if "warmup" in given:
        for w in WORKLOADS:
            opts[f"warmup_{w}"] = given.get(f"warmup_{w}", given["warmup"])
    return opts


def main(argv: Sequence[str] | None = None) -> None:
    args, given = pop_bench_options(sys.argv[1:] if argv is None else argv)
    job = args[0] if args else ""
    opts = job_options(job, given)
    jobs = {
        "env": lambda cfg: bench_env(cfg, opts),
        "planner": lambda cfg: bench_planner_share(cfg, opts["steps"], opts["warmup"]),
    }
    result = run_tool(jobs, args, usage=USAGE)
    print(strict_json.dumps(result, indent=2), flush=True)
