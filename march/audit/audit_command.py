"""``python -m march.audit <job>``: the science checks that need no GPU (issue 50).

    python -m march.audit rewards [reward=clf|modelfree] [teacher_ckpt=<file>] [out=<file>.json]
    python -m march.audit reference [out=<file>.json]
    python -m march.audit envelope [out=<file>.json]

Every job composes the same config as ``march.train`` and takes its ``key=value`` overrides
(``compute.num_envs``, ``seed``, ``+experiment=...``); it prints a table and writes strict JSON
plus a PNG beside it (``out=``, default ``outputs/audit/<job>_<reward>.json``).

- ``rewards`` (:mod:`march.audit.reward_audit`): the arm's training env, canonical behaviours rolled
  from the same seeds, every reward term's return, V/Vmax, distance, falls, and the verdict
  "does this reward rank tracking above standing?" with a 95 % interval over rollouts.
- ``reference`` (:mod:`march.audit.feasibility`): the G1's whole-body IK along planned
  references at every curriculum level: the error floor per output and of V/Vmax under perfect
  kinematic tracking, and where the plan is out of the G1's reach.
- ``envelope`` (:mod:`march.audit.reach_envelope`): the longest step whose touchdown pose the
  G1 can take, against the CoM height.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path

from march.config import MarchConfig
from march.config.cli import fail, run_tool

USAGE = (
    "usage: python -m march.audit rewards|reference|envelope [out=<file>.json] "
    "[teacher_ckpt=<file>] "
    "[key=value ...]"
)


def _out(cfg: MarchConfig, job: str) -> Path:
    out = Path(cfg.out or f"outputs/audit/{job}_{cfg.reward.name}.json")
    if out.suffix != ".json":
        fail(f"out={out}: give a .json file (the PNG is written beside it)")
    return out


def _read_teacher(cfg: MarchConfig) -> dict:
    """``teacher_ckpt=`` through the disk gate (:func:`march.store.gate.read_checkpoint`: no
    link, bounded size, config and weights checked, named modules consented), before any env;
    a checkpoint of another reward arm is refused in one line (its observations are that arm's)."""
    from march.errors import ConfigError
    from march.store.checkpoint import CheckpointError
    from march.store.gate import read_checkpoint

    try:
        payload, saved = read_checkpoint(
            cfg.teacher_ckpt, "teacher", cfg.extra_modules, cfg.compute.device
        )
    except (CheckpointError, ConfigError) as err:
        fail(str(err))
    if saved is not None and saved.reward.name != cfg.reward.name:
        fail(
            f"teacher_ckpt={cfg.teacher_ckpt} was trained with reward={saved.reward.name}; "
            f"audit it with reward={saved.reward.name} (its observations are that arm's)"
        )
    return payload


def rewards(cfg: MarchConfig) -> dict:
    from march.audit.report import figure, table, write_json
    from march.audit.reward_audit import audit_arm
    from march.env.build import make_env

    out = _out(cfg, "rewards")
    payload = _read_teacher(cfg) if cfg.teacher_ckpt else None
    env = make_env(cfg, "teacher", log=out.with_suffix(".env.log"))
    policy = None
    if payload is not None:
        from march.evaluation.protocol import policy_from_checkpoint

        policy = policy_from_checkpoint(env, cfg, "teacher", payload, cfg.teacher_ckpt)
    arm = audit_arm(env, cfg, policy)
    print(table(arm))
    write_json(arm, out)
    png = figure(arm, out.with_suffix(".png"))
    print(f"wrote {out} and {png}")
    return arm


def reference(cfg: MarchConfig) -> dict:
    from march.audit.feasibility import reference_report

    return reference_report(cfg, str(_out(cfg, "reference")))


def envelope(cfg: MarchConfig) -> dict:
    from march.audit.reach_envelope import envelope_report

    return envelope_report(cfg, str(_out(cfg, "envelope")))


JOBS = {"rewards": rewards, "reference": reference, "envelope": envelope}


def main(argv: Sequence[str] | None = None) -> None:
    from march.store.checkpoint_file import check_checkpoint_files

    # teacher_ckpt= judged (link, size, zip records) before the term check loads the simulator
    run_tool(JOBS, argv, usage=USAGE, before_terms=check_checkpoint_files)


if __name__ == "__main__":
    main(sys.argv[1:])
