"""``python -m march.audit <job>``: the science checks that need no GPU (issue 50).

    python -m march.audit rewards [reward=clf|modelfree] [teacher_ckpt=<file>] [out=<file>.json]
    python -m march.audit reference [out=<file>.json] [audit.<option>=...]
    python -m march.audit envelope [out=<file>.json] [audit.<option>=...]

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

``audit.<option>=value`` sets the kinematic audits' own options (``reference`` and
``envelope``; :data:`AUDIT_OPTIONS`): ``audit.stance=flat|heel_off|heel_toe`` (the stance
foot's contact model, :class:`march.audit.kinematic_g1.IkCfg`), ``audit.heel_pitch_max``
[rad], ``audit.heel_cost`` [1/rad], ``audit.heel_flat_by`` [-], and for ``reference``
``audit.courses_per_level`` and ``audit.film=true|false``. The reach tolerances are not options here: they are the audit's
judgement. A bad value is one line on stderr and exit 2, before anything is built.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from march.config import MarchConfig
from march.config.cli import fail, run_tool

USAGE = (
    "usage: python -m march.audit rewards|reference|envelope [out=<file>.json] "
    "[teacher_ckpt=<file>] [audit.stance=flat|heel_off|heel_toe] "
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


AUDIT_OPTIONS: dict[str, tuple[str, type, tuple[str, ...]]] = {
    "stance": ("ik", str, ("reference", "envelope")),
    "heel_pitch_max": ("ik", float, ("reference", "envelope")),
    "heel_cost": ("ik", float, ("reference", "envelope")),
    "heel_flat_by": ("ik", float, ("reference", "envelope")),
    "courses_per_level": ("feasibility", int, ("reference",)),
    "film": ("feasibility", bool, ("reference",)),
}
"""``audit.<key>``: which config it sets (``IkCfg`` or ``FeasibilityCfg``), its type, and the
jobs that take it."""


@dataclass
class AuditOptions:
    """The ``audit.*`` overrides of one command line, by the config they set."""

    ik: dict = field(default_factory=dict)
    feasibility: dict = field(default_factory=dict)


def parse_value(key: str, kind: type, text: str) -> object:
    if kind is bool:
        if text.lower() not in ("true", "false"):
            fail(f"audit.{key}={text}: give true or false")
        return text.lower() == "true"
    try:
        return kind(text)
    except ValueError:
        fail(f"audit.{key}={text}: give a {kind.__name__}")
    return None  # unreachable: fail exits


def split_audit_options(args: list[str]) -> tuple[list[str], AuditOptions]:
    """The command line without its ``audit.*`` overrides, and those parsed (the job first,
    then key=value: one line and exit 2 on an unknown key, a value of the wrong type or a key
    the job does not take; the values' ranges are :func:`check_audit_options`'s)."""
    job = args[0] if args and "=" not in args[0] else None
    rest, options = [], AuditOptions()
    for arg in args:
        key, sep, text = arg.partition("=")
        if not (sep and key.startswith("audit.")):
            rest.append(arg)
            continue
        name = key.removeprefix("audit.")
        if name not in AUDIT_OPTIONS:
            fail(f"{key}: unknown audit option; choose one of {', '.join(AUDIT_OPTIONS)}")
        target, kind, jobs = AUDIT_OPTIONS[name]
        if job not in jobs:
            fail(f"{key} applies to {' and '.join(jobs)}, not to {job or 'no job'}")
        if name in getattr(options, target):
            fail(f"{key} is given twice; keep one")
        getattr(options, target)[name] = parse_value(name, kind, text)
    return rest, options


def check_audit_options(options: AuditOptions) -> None:
    """The ``audit.*`` values checked by their configs (raises :class:`ConfigError`). Run after
    the file gate and before anything is built: the configs' modules import torch, so a crafted
    checkpoint is refused before they load (issue 59), and none load when no option is given."""
    if not (options.ik or options.feasibility):
        return
    from march.audit.feasibility import FeasibilityCfg
    from march.audit.kinematic_g1 import IkCfg

    IkCfg(**options.ik)
    FeasibilityCfg(**options.feasibility)


def reference(cfg: MarchConfig, options: AuditOptions | None = None) -> dict:
    from march.audit.feasibility import FeasibilityCfg, reference_report
    from march.audit.kinematic_g1 import IkCfg

    options = options or AuditOptions()
    return reference_report(
        cfg,
        str(_out(cfg, "reference")),
        FeasibilityCfg(**options.feasibility),
        IkCfg(**options.ik),
    )


def envelope(cfg: MarchConfig, options: AuditOptions | None = None) -> dict:
    from march.audit.kinematic_g1 import IkCfg
    from march.audit.reach_envelope import envelope_report

    options = options or AuditOptions()
    return envelope_report(cfg, str(_out(cfg, "envelope")), ik=IkCfg(**options.ik))


JOBS = {"rewards": rewards, "reference": reference, "envelope": envelope}


def main(argv: Sequence[str] | None = None) -> None:
    from march.store.checkpoint_file import check_checkpoint_files

    args, options = split_audit_options(list(sys.argv[1:] if argv is None else argv))
    jobs = {
        "rewards": rewards,
        "reference": lambda cfg: reference(cfg, options),
        "envelope": lambda cfg: envelope(cfg, options),
    }

    def before_terms(tree: object) -> None:
        check_checkpoint_files(tree)  # link, size, zip records: before torch is imported
        check_audit_options(options)  # then the audit.* values, before anything is built

    run_tool(jobs, args, usage=USAGE, before_terms=before_terms)


if __name__ == "__main__":
    main(sys.argv[1:])
