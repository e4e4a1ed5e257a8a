"""``python -m march.inspect <overrides>``: build the composed env (no training), print JSON.

Observation groups and shapes (teacher ``actor``, ``critic``, ``student``, ``depth``), reward terms
with weights, terminations, events (domain randomization) with their ranges, terrain and camera,
and the pieces that are still placeholders. How a researcher checks a config before spending GPU
hours. ``python -m march.inspect budget compute=gpu``: what those GPU hours are, per stage and
sweep (:mod:`march.learn.budget`). ``python -m march.inspect run <run dir>``: the run's status
as it truly is (a ``running`` run whose process is gone reads ``killed``), what its config.yaml
names, and its newest checkpoints with their iterations (every file read through the gate).
"""

from __future__ import annotations

import contextlib
import json
import math
import sys
from typing import Any

import numpy as np

from march.config import MarchConfig
from march.config.cli import run_tool


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, float):
        return value if math.isfinite(value) else str(value)
    if isinstance(value, (int, str, bool)) or value is None:
        return value
    if callable(value):
        return getattr(value, "__name__", type(value).__name__)  # a class term: its class
    if hasattr(value, "name") and hasattr(value, "body_names"):  # SceneEntityCfg
        parts = {
            k: getattr(value, k)
            for k in ("name", "body_names", "joint_names", "geom_names", "site_names")
            if getattr(value, k, None) not in (None, (), [])
        }
        return _jsonable(parts)
    return repr(value)


def describe_env(env: Any) -> dict[str, Any]:
    """The JSON-able description of a built mjlab env."""
    om, rm, tm, em = (
        env.observation_manager,
        env.reward_manager,
        env.termination_manager,
        env.event_manager,
    )
    observations = {
        group: {
            "shape": list(om.group_obs_dim[group]),
            "terms": {
                name: list(dim)
                for name, dim in zip(
                    om.active_terms[group], om.group_obs_term_dim[group], strict=True
                )
            },
        }
        for group in om.active_terms
    }
    rewards = [{"name": n, "weight": rm.get_term_cfg(n).weight} for n in rm.active_terms]
    terminations = [
        {
            "name": n,
            "time_out": tm.get_term_cfg(n).time_out,
            "params": _jsonable(tm.get_term_cfg(n).params),
        }
        for n in tm.active_terms
    ]
    events = []
    for mode, names in em.active_terms.items():
        for n in names:
            term = em.get_term_cfg(n)
            entry = {
                "name": n,
                "mode": mode,
                "func": _jsonable(term.func),
                "params": _jsonable(term.params),
            }
            if term.interval_range_s is not None:  # the push is a step event with its timers
                entry["interval_range_s"] = _jsonable(term.interval_range_s)
            events.append(entry)
    return {
        "num_envs": env.num_envs,
        "step_dt_s": env.step_dt,
        "episode_length_s": env.max_episode_length_s,
        "num_actions": env.action_manager.total_action_dim,
        "observations": observations,
        "rewards": rewards,
        "terminations": terminations,
        "events": events,
    }


def terrain_summary(cfg: MarchConfig, table: Any) -> dict[str, Any]:
    """Levels with their sampling ranges and what the compiled courses actually contain."""
    from march.world.courses import ROLE_PAIR, ROLE_STONE, difficulty_ranges

    stone_roles = (ROLE_STONE, ROLE_PAIR)

    levels = []
    for row, layouts in enumerate(table.layouts):
        d = float(table.difficulty[row, 0])
        r = difficulty_ranges(d, cfg.terrain)
        stones = [lay for lay in layouts if lay.kind != "flat"]
        n_steps = sum(lay.num_steps for lay in stones)
        n_pairs = sum(lay.num_pairs for lay in stones)
        levels.append(
            {
                "level": row,
                "difficulty": round(d, 3),
                "kind": "flat" if not stones else "stones",
                "stone_size_m": list(r.stone_size) if stones else None,
                "gap_m": list(r.gap) if stones else None,
                "height_variation_m": r.height if stones else None,
                "lateral_zigzag_m": list(r.lateral) if stones else None,
                "pair_fraction": round(n_pairs / n_steps, 3) if n_steps else None,
                "stones_per_course": (
                    round(
                        sum(int(np.isin(lay.role, stone_roles).sum()) for lay in stones)
                        / len(stones),
                        1,
                    )
                    if stones
                    else 0
                ),
            }
        )
    return {
        "cells": list(table.shape) if hasattr(table, "shape") else None,
        "cell_size_m": list(cfg.terrain.size),
        "curriculum": cfg.curriculum.name,
        "pair_probability": cfg.terrain.pair_prob,
        "pit_depth_m": cfg.terrain.pit_depth,
        "levels": levels,
    }


def inspect(cfg: MarchConfig) -> dict[str, Any]:
    from dataclasses import asdict

    from march.env.build import PLACEHOLDERS, build_env_cfg, make_env
    from march.env.course import foothold_table
    from march.env.randomization import describe_dr

    # mjlab and warp report to stdout while building: keep stdout for the JSON alone.
    with contextlib.redirect_stdout(sys.stderr):
        env = make_env(cfg, "eval", num_envs=2)
        table = foothold_table(env)
    report = {
        "config": {
            "stage": cfg.stage,
            "reward": cfg.reward.name,
            "student": cfg.student.variant,
            "curriculum": cfg.curriculum.name,
            "compute": cfg.compute.name,
            "device": cfg.compute.device,
            "dr": cfg.dr.name,
            "seed": cfg.seed,
        },
        "placeholders": PLACEHOLDERS,
        **describe_env(env),
        "camera": {**_jsonable(asdict(cfg.depth)), "parent_body": "torso_link"},
        "domain_randomization": _jsonable(describe_dr(cfg.dr, cfg.depth.name, cfg.depth)),
        "terrain": terrain_summary(cfg, table),
    }
    # The built env is the eval env (it has every observation group); training ends episodes
    # on more terms than evaluation (time-out and falls only), so list both.
    report["eval_terminations"] = report["terminations"]
    report["terminations"] = [
        {"name": n, "time_out": t.time_out, "params": _jsonable(t.params)}
        for n, t in build_env_cfg(cfg, "teacher").terminations.items()
    ]
    env.close()
    return report


BUDGET_USAGE = (
    "usage: python -m march.inspect budget [compute=gpu] [budget.bench=BENCH_JSON] "
    "[budget.check=GPU_CHECK_JSON] [budget.json=true] [key=value ...]"
)


def budget_job(argv: list[str]) -> None:
    """``budget``: the pipeline's estimated GPU hours (march.learn.budget), a Markdown table
    (``budget.json=true``: the JSON)."""
    from pathlib import Path

    from march.config.cli import fail
    from march.learn.budget import budget, table

    opts = {
        a.split("=", 1)[0][len("budget.") :]: a.split("=", 1)[1]
        for a in argv
        if a.startswith("budget.") and "=" in a
    }
    rest = [a for a in argv if not a.startswith("budget.")]
    bad = set(opts) - {"bench", "check", "json"} or {
        a for a in argv if a.startswith("budget.") and "=" not in a
    }
    if bad:
        fail(f"unknown budget option(s) {sorted(bad)}. {BUDGET_USAGE}")
    for key in ("bench", "check"):
        if key in opts and not Path(opts[key]).is_file():
            fail(f"budget.{key}={opts[key]}: no such file")

    def job(cfg: MarchConfig) -> None:
        report = budget(
            cfg,
            Path(opts["bench"]) if "bench" in opts else None,
            Path(opts["check"]) if "check" in opts else None,
        )
        print(json.dumps(report, indent=2) if opts.get("json") == "true" else table(report))

    run_tool(job, rest, usage=BUDGET_USAGE)


def list_job(argv: list[str]) -> None:
    """``python -m march.inspect list``: every term, arm, part, variant and sweep a run can name
    (march.config.listing), ``extra_modules`` and ``hydra.searchpath`` included."""
    from march.config.listing import collect, render
    from march.config.registry import searchpath_dirs

    def job(cfg: MarchConfig) -> None:
        print(render(collect(cfg.extra_modules, searchpath_dirs(argv))))

    run_tool(job, argv, usage="usage: python -m march.inspect list [extra_modules=[...]] [...]")


def run_job(argv: list[str]) -> None:
    """``python -m march.inspect run <run dir>``: as JSON, the run's status as its readers see it
    (march.store.status: ``running`` with its pid gone on this host reads ``killed``), what its
    config.yaml names (stage, reward, student, seed) and, for its newest teacher and student
    checkpoints, their path, iteration and env steps. Every file is read through the gate
    (config.yaml without YAML aliases, checkpoints through :func:`march.store.checkpoint.
    load_checkpoint`: no link, bounded, zip records checked, plain data); a file it refuses is
    one line, exit 2. Builds no env."""
    from pathlib import Path

    from omegaconf import OmegaConf

    from march.config.cli import fail
    from march.store.bounded_read import FileRefused, read_yaml_text
    from march.store.checkpoint_file import CheckpointError, check_file, latest_checkpoint
    from march.store.status import read_status

    if len(argv) != 1 or not Path(argv[0]).is_dir():
        fail("usage: python -m march.inspect run <run dir>")
    run = Path(argv[0])
    report: dict[str, Any] = {"run": str(run), "status": read_status(run), "config": None}
    try:
        if (run / "config.yaml").is_file() or (run / "config.yaml").is_symlink():
            path = run / "config.yaml"
            text = read_yaml_text(path, str(path))  # no alias, bounded
            tree = OmegaConf.to_container(OmegaConf.create(text), resolve=False)  # nothing run

            def get(key: str) -> Any:
                node: Any = tree
                for part in key.split("."):
                    node = node.get(part) if isinstance(node, dict) else None
                return node

            keys = ("stage", "reward.name", "student.variant", "seed")
            report["config"] = {k: get(k) for k in keys}
        newest = {
            kind: latest_checkpoint(run / kind) if (run / kind).is_dir() else None
            for kind in ("teacher", "student")
        }
        for found in newest.values():
            if found is not None:  # every file's zip directory, before torch is imported
                check_file(found, str(found))
        for kind, found in newest.items():
            entry = None
            if found is not None:
                from march.store.checkpoint import load_checkpoint  # torch

                payload = load_checkpoint(found, kind, source=str(found))
                entry = {
                    "path": str(found),
                    "iteration": payload.get("iteration"),
                    "env_steps": payload.get("env_steps"),
                }
            report[f"{kind}_checkpoint"] = entry
    except (FileRefused, CheckpointError) as err:
        fail(str(err))
    except Exception as err:  # noqa: BLE001 - a config.yaml OmegaConf cannot build
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        fail(f"{run / 'config.yaml'}: cannot be read ({first})")
    print(json.dumps(report, indent=2))


def main() -> None:
    def job(cfg: MarchConfig) -> None:
        report = inspect(cfg)
        print(json.dumps(report, indent=2))

    if sys.argv[1:2] == ["budget"]:
        budget_job(sys.argv[2:])
        return
    if sys.argv[1:2] == ["list"]:
        list_job(sys.argv[2:])
        return
    if sys.argv[1:2] == ["run"]:
        run_job(sys.argv[2:])
        return
    run_tool(
        job,
        usage="usage: python -m march.inspect [key=value ...] | budget [key=value ...] | list "
        "| run <run dir>",
    )


if __name__ == "__main__":
    main()
