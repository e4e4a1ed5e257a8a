"""What the GPU check (``scripts/gpu_check.py``) reads of its phases' files: the bench's JSON
(final or partial), the sync check's file, learning-curve rows, compiled vs eager benches and
the targets judged on them. Plain functions of files and dicts, tested on CPU
(``tests/test_bench.py``).
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

from march.bench.targets import STEP_TARGETS, SYNC_TARGETS
from march.store.bounded_read import FileRefused, read_bytes, read_json

MAX_SYNCS_BYTES = 256 << 20
"""``syncs.tsv``: one line per recorded sync (a few MB for the check's phases)."""


def read_rows(path: Path, stage: str) -> list[dict[str, str]]:
    """The rows of ``stage`` in a run table, read through the gate
    (:func:`march.store.run_tables.read_table`: no link, bounded, every row checked)."""
    from march.store.run_tables import read_table

    table = read_table(path)
    return [] if table is None else [r for r in table.rows if r.get("stage") == stage]


def write_rows(rows: list[dict[str, str]], path: Path) -> None:
    if not rows:
        return
    keys = list(rows[0])
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)


def number(text: str | None) -> float | None:
    """A CSV cell as a float; None for an empty cell (no episode ended yet: NaN in the log)."""
    try:
        return float(text) if text not in (None, "") else None
    except ValueError:
        return None


BENCH_KEYS = (
    "num_envs",
    "ratio_march_vs_rough_by_workload",
    "build_s",
    "ops_per_step",
    "ratio_ops_march_vs_rough",
    "nonphysics_ms_per_step",
    "ratio_ops_march_vs_rough_cuda_path",
    "ratio_nonphysics_march_vs_rough",
    "min_ratio_march_vs_rough",
    "targets",
    "compile",
)
"""What ``gpu_check.json`` keeps of the bench's JSON (and ``steps_per_s`` per workload)."""


def bench_results(
    out: Path, finished: bool, stem: str = "bench_env"
) -> tuple[dict[str, Any] | None, list[str], str]:
    """The bench phase's figures for ``gpu_check.json``, its result files and a note. From
    ``bench_env.json`` when the phase finished; otherwise (failed, or stopped by its time
    limit) from ``bench_env.partial.json``, which the bench rewrites after each workload, so a
    first GPU run that runs out of time still reports the workloads it finished."""
    for name, usable in ((f"{stem}.json", finished), (f"{stem}.partial.json", True)):
        path = out / name
        if not usable or not path.is_file():
            continue
        try:
            bench = read_json(path, str(path), wanted="the bench's JSON")
            summary = {k: bench.get(k) for k in BENCH_KEYS}
            summary["steps_per_s"] = {w: v["steps_per_s"] for w, v in bench["workloads"].items()}
        except (FileRefused, KeyError, TypeError, AttributeError) as err:
            return None, [], f"unreadable {name}: {err}"
        if name == f"{stem}.json":
            return summary, [name], ""
        done = bench.get("completed_workloads", [])
        summary["completed_workloads"] = done
        return summary, [name], f"partial results: {', '.join(done) or 'no workload'} finished"
    return None, [], ""


def sync_results(path: Path) -> dict[str, Any]:
    """What ``gpu_check.json`` keeps of ``syncs.tsv``: syncs recorded, those with march code on
    the stack, whether CUDA recorded anything, the phases in the file and their env steps; the
    march source lines that synced in more than one env step of a part (a read once per
    iteration falls in one step: it is listed in the file, not here); and the syncs per env
    step of march's env and bare rough's, stepped alone (once both are recorded)."""
    lines = read_bytes(path, str(path), MAX_SYNCS_BYTES, "syncs.tsv").decode().splitlines()
    rows = [ln.split("\t") for ln in lines if ln and not ln.startswith(("#", "phase"))]
    rows = [r for r in rows if len(r) >= 4]

    def header(key: str) -> list[str]:
        text = next((ln.split(":", 1)[1] for ln in lines if ln.startswith(f"# {key}:")), "")
        return [p.strip() for p in text.split(",") if p.strip()]

    steps = {k: int(v) for k, _, v in (p.rpartition(" ") for p in header("steps")) if k}
    in_steps: dict[tuple[str, str], set[str]] = {}
    for ph, step, src, *_ in rows:
        if src.startswith("march/") and step != "0":
            in_steps.setdefault((ph, src), set()).add(step)
    result: dict[str, Any] = {
        "recorded": len(rows),
        "with_march_on_stack": sum(1 for r in rows if r[3] != "-"),
        "cuda": not (lines and lines[0].startswith("# no CUDA")),
        "phases": header("recorded"),
        "steps": steps,
        "march_lines_per_step": sorted(
            f"{ph} {src}" for (ph, src), s in in_steps.items() if len(s) > 1
        ),
    }
    if "env_march" in steps and "env_rough" in steps:
        result["env_syncs_per_step"] = {
            env: sum(1 for r in rows if r[0] == f"env_{env}") / max(steps[f"env_{env}"], 1)
            for env in ("march", "rough")
        }
    return result


def compile_vs_eager(
    compiled: dict[str, Any],
    eager: dict[str, Any],
    names: tuple[str, str] = ("compiled", "eager"),
) -> dict[str, Any]:
    """What ``compute.compile_math`` gains on this machine, per workload both benches finished:
    march's env steps per second and non-physics ms per step, compiled and eager, and their
    ratios (compiled / eager: above 1 for the speed, below 1 for the time, where it wins).
    ``names``: the two benches' labels (``("graphs", "default")`` for
    ``compute.compile_mode=reduce-overhead`` against the default mode)."""
    first, second = names
    both = {first: compiled, second: eager}

    def march(key: str, workload: str) -> dict[str, Any]:
        """March's figure ``key`` of ``workload`` in each bench (None where it lacks it)."""
        return {
            k: ((b.get(key) or {}).get(workload) or {}).get("march_teacher")
            for k, b in both.items()
        }

    out: dict[str, Any] = {}
    for w in sorted(set(compiled.get("steps_per_s") or {}) & set(eager.get("steps_per_s") or {})):
        speed = march("steps_per_s", w)
        row: dict[str, Any] = {
            "steps_per_s": speed,
            "speed_ratio": speed[first] / speed[second],
        }
        times = march("nonphysics_ms_per_step", w)
        if all(times.values()):
            row["nonphysics_ms"] = times
            row["nonphysics_ratio"] = times[first] / times[second]
        out[w] = row
    return out


def judged_targets(results: dict[str, Any]) -> dict[str, Any]:
    """The step's speed targets as the bench judged them (each not measured where the bench
    phase left no figure), and the sync targets, judged only where CUDA recorded the syncs
    (:mod:`march.bench.targets`): no march source line that syncs in more than one env step of
    a part (teacher rollout, distillation rollout, march's env), and march's env no more syncs
    per step than bare rough's."""
    bench = (results.get("bench") or {}).get("targets") or {}
    judged = {t.key: bench.get(t.key) or t.judge(None) for t in STEP_TARGETS}
    syncs = results.get("syncs") or {}
    lines = syncs.get("march_lines_per_step") if syncs.get("cuda") and syncs.get("phases") else None
    per_step = syncs.get("env_syncs_per_step") if syncs.get("cuda") else None
    extra = per_step["march"] - per_step["rough"] if per_step else None
    lines_target, env_target = SYNC_TARGETS
    judged[lines_target.key] = lines_target.judge(None if lines is None else len(lines))
    judged[env_target.key] = env_target.judge(extra)
    return judged


def seconds_per_iteration(rows: list[dict[str, str]]) -> float | None:
    """A training run's seconds per iteration from its second iteration on: the ``wall_s`` from
    the end of the first logged iteration to the end of the last, over the iterations between
    (the first pays the lazy set-ups and, compiled, the first graphs). None with < 2 rows."""
    if len(rows) < 2:
        return None
    first, last = rows[0], rows[-1]
    n = int(last["iteration"]) - int(first["iteration"])
    return (float(last["wall_s"]) - float(first["wall_s"])) / n if n > 0 else None
