"""Where a step's non-physics time goes: a picture of a ``python -m march.bench env`` result.

Usage::

    python analysis/bench_figure.py BENCH_JSON_OR_DIR [MORE ...] [--out DIR]

A directory stands for the bench JSONs in it (``bench_env*.json`` of a GPU check's folder; a
partial file only where the final one is missing or unreadable). Per JSON, ``<stem>.png`` (and
``.pdf``) in ``--out`` (default: beside the JSON): one panel per workload, a stacked bar per env
(march teacher, bare rough, bare flat) of the profile pass's exclusive ms per control step by
category, physics left out and the footstep planner apart from the other commands, at the first
timed thread count; a dashed line at the non-physics target's bound times bare rough's time
(the bound the bench judged, ``targets`` in its JSON; 1.5 for older JSONs without it); each
env's label carries its compute ops per step. The title names the device, the envs and the targets the bench judged.
``<stem>_data.csv`` holds every bar segment (workload, env, category, ms) so that the picture can
be read back number by number.

This script reads files only (pandas, matplotlib), never the simulator or the ``march`` package.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pandas as pd  # noqa: E402

if __package__ in (None, ""):  # run as a script: make ``march`` importable from a checkout
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from march.store.bounded_read import FileRefused, read_json  # noqa: E402

ENVS = ("march_teacher", "bare_rough", "bare_flat")
"""The bench's envs, in the order drawn."""
PLANNER = "commands: planner"
"""The footstep planner's share of ``commands`` (the profile's ``commands/planner`` section)."""
CATEGORIES = (
    PLANNER,
    "commands",
    "observations",
    "rewards",
    "terminations",
    "actions",
    "events",
    "resets",
    "curriculum",
    "other",
)
"""The profile's non-physics categories, in stacking order (others, if any, go last)."""
SHORT = {
    "ratio_ops_march_vs_rough": "ops",
    "ratio_nonphysics_march_vs_rough": "non-physics",
    "min_ratio_march_vs_rough": "speed",
}
"""The title's names of the bench's targets (march / bare rough ratios)."""
NONPHYSICS_BOUND = 1.5
"""march.bench.targets' bound on march / bare rough's non-physics time, for a bench JSON from
before the bench judged its targets (a newer one carries the bound it judged)."""


def bench_files(paths: list[Path]) -> list[Path]:
    """The bench JSONs named, a directory standing for its ``bench_env*.json``: a partial file
    only where its final file is missing or unreadable (a bench stopped while it printed)."""
    found: list[Path] = []
    for path in paths:
        if not path.is_dir():
            found.append(path)
            continue
        names = sorted(path.glob("bench_env*.json"))
        finals = {p.name for p in names if not p.name.endswith(".partial.json") and _readable(p)}
        for p in names:
            if p.name.endswith(".partial.json"):
                if p.name.replace(".partial.json", ".json") not in finals:
                    found.append(p)
            elif p.name in finals:
                found.append(p)
    return found


def read_bench(path: Path) -> dict:
    """A bench JSON through march's gate (:func:`march.store.bounded_read.read_json`: no link,
    bounded, strict); :class:`~march.store.bounded_read.FileRefused` in one line."""
    data = read_json(path, str(path), wanted="a JSON file python -m march.bench wrote")
    if not isinstance(data, dict):
        raise FileRefused(f"{path}: not a JSON object")
    return data


def _readable(path: Path) -> bool:
    try:
        read_bench(path)
    except FileRefused:
        return False
    return True


def segments(bench: dict) -> pd.DataFrame:
    """One row per bar segment: workload, env, category, ms (non-physics categories of the
    profile at the first timed thread count, the planner's section apart from the rest of
    ``commands``); empty where the bench ran no profile pass."""
    rows = []
    for workload, result in (bench.get("workloads") or {}).items():
        for env, prof in (result.get("profile") or {}).items():
            planner = (prof.get("sections_ms") or {}).get("commands/planner", 0.0)
            for category, ms in (prof.get("categories_ms") or {}).items():
                if category == "physics":
                    continue
                if category == "commands" and planner > 0:
                    rows.append(
                        {"workload": workload, "env": env, "category": PLANNER, "ms": planner}
                    )
                    ms -= planner
                rows.append({"workload": workload, "env": env, "category": category, "ms": ms})
    return pd.DataFrame(rows, columns=["workload", "env", "category", "ms"])


def _title(bench: dict) -> str:
    judged = bench.get("targets") or {}
    verdicts = []
    for key, j in judged.items():
        if j.get("value") is None:
            continue
        name = SHORT.get(key, key)
        bound = f"{'<=' if 'at_most' in j else '>='} {j.get('at_most', j.get('at_least'))}"
        state = "met" if j.get("met") else "NOT MET"
        verdicts.append(f"{name} {j['value']:.2f} ({bound}) {state}")
    head = f"march.bench env: {bench.get('device', '?')}, {bench.get('num_envs', '?')} envs"
    threads = bench.get("threads") or []
    if threads:
        head += f", profile at {threads[0]} thread(s)"
    return head + ("\n" + "; ".join(verdicts) if verdicts else "")


def draw(bench: dict, stem: Path) -> list[Path]:
    """``stem``.png/.pdf and ``stem``_data.csv for one bench result; [] without a profile."""
    data = segments(bench)
    if data.empty:
        return []
    workloads = list(dict.fromkeys(data["workload"]))
    order = [c for c in CATEGORIES if c in set(data["category"])]
    order += sorted(set(data["category"]) - set(order))
    colours = dict(zip(order, plt.get_cmap("tab10").colors, strict=False))
    fig, axes = plt.subplots(
        len(workloads), 1, figsize=(8.0, 1.2 + 1.6 * len(workloads)), squeeze=False
    )
    ops = bench.get("ops_per_step") or {}
    judged = (bench.get("targets") or {}).get("ratio_nonphysics_march_vs_rough") or {}
    bound = judged.get("at_most", NONPHYSICS_BOUND)
    for ax, workload in zip(axes[:, 0], workloads, strict=True):
        rows = data[data["workload"] == workload]
        envs = [e for e in ENVS if e in set(rows["env"])]
        labels = []
        for y, env in enumerate(envs):
            left = 0.0
            for category in order:
                ms = float(rows[(rows["env"] == env) & (rows["category"] == category)]["ms"].sum())
                if ms > 0:
                    ax.barh(y, ms, left=left, color=colours[category], label=category)
                    left += ms
            n_ops = (ops.get(workload) or {}).get(env)
            labels.append(env + (f"\n{n_ops:.0f} ops/step" if n_ops is not None else ""))
        ax.set_yticks(range(len(envs)), labels)
        ax.invert_yaxis()
        rough = float(rows[rows["env"] == "bare_rough"]["ms"].sum())
        if rough > 0:
            ax.axvline(bound * rough, color="k", linestyle="--", linewidth=1)
            ax.text(
                bound * rough,
                -0.6,
                f" {bound:g}x rough",
                fontsize=8,
                va="bottom",
            )
        ax.set_title(workload, fontsize=10, loc="left")
        ax.set_xlabel("non-physics ms per control step (profile pass)")
    handles, names = axes[0, 0].get_legend_handles_labels()
    unique = dict(zip(names, handles, strict=True))
    fig.legend(unique.values(), unique.keys(), loc="lower center", ncol=5, fontsize=8)
    fig.suptitle(_title(bench), fontsize=9)
    fig.tight_layout(rect=(0, 0.08, 1, 1))
    written = []
    for ext in ("png", "pdf"):
        path = stem.with_suffix(f".{ext}")
        fig.savefig(path, dpi=120)
        written.append(path)
    plt.close(fig)
    csv = stem.with_name(stem.name + "_data.csv")
    data.to_csv(csv, index=False)
    return [*written, csv]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("paths", nargs="+", type=Path, help="bench JSONs or folders holding them")
    p.add_argument("--out", type=Path, default=None, help="folder for the figures")
    args = p.parse_args(argv)
    files = bench_files(args.paths)
    missing = [f for f in files if not f.is_file()]
    if missing or not files:
        print(f"bench_figure: no bench JSON at {', '.join(map(str, missing or args.paths))}")
        return 2
    status = 0
    for path in files:
        try:
            bench = read_bench(path)
        except FileRefused as err:
            print(f"bench_figure: not a bench JSON ({err})")
            status = 2
            continue
        out = args.out or path.parent
        out.mkdir(parents=True, exist_ok=True)
        written = draw(bench, out / path.name.removesuffix(".json"))
        if written:
            print(f"bench_figure: {path} -> {', '.join(str(w) for w in written)}")
        else:
            print(f"bench_figure: {path}: no profile pass (bench.profile_steps=0), nothing drawn")
    return status


if __name__ == "__main__":
    sys.exit(main())
