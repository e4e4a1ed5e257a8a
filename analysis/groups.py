"""Which runs may be pooled: the group key, duplicate seeds, and the series names figures draw.

The unit of replication is the seed (a training run). Runs are pooled into one point only when
everything that defines the experiment is equal: :class:`GroupKey` = (reward arm, whether the
teacher observes the reference, curriculum, teacher budget in iterations, distillation budget,
compute preset, student variant, stage, the checkpoints a run started from). ``stage`` separates
students distilled from their own teacher (``all``) from students of a fixed teacher checkpoint
(the ablation sweep, ``student``); the checkpoints separate ablations of two teachers and
evaluations of two policies (``teacher_ckpt`` / ``student_ckpt``).
Two runs with the same key and seed are the same experiment twice (a killed duplicate, a re-run
in another folder): pooling them would count a seed twice, so :func:`group_runs` refuses them in
one line naming the runs, or, asked to (``--allow-duplicates``), keeps the newest and says so.

Series names: a group is named by its reward arm, followed in brackets by what tells it apart
from the other groups of the same arm in the same figure (``modelfree [stones, 2 it]``,
``clf [cpu]``). Reads files only; never imports march.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path

from omegaconf import OmegaConf

from analysis.rundirs import Run

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"


class DuplicateRunsError(ValueError):
    """Two runs of one group share a seed (the message is the one line to print)."""


@dataclass(frozen=True)
class GroupKey:
    reward: str
    observe_reference: bool
    curriculum: str
    teacher_budget: object
    distill_budget: object
    compute: str
    variant: str
    stage: str
    checkpoints: str = ""

    @classmethod
    def of(cls, run: Run) -> GroupKey:
        return cls(
            reward=run.reward,
            observe_reference=bool(run.observe_reference),
            curriculum=run.curriculum,
            teacher_budget=run.teacher_budget,
            distill_budget=run.distill_budget,
            compute=run.compute,
            variant=run.variant,
            stage=run.stage,
            checkpoints=run.checkpoints,
        )

    def teacher_part(self) -> GroupKey:
        """The key of the teacher alone: variant and distillation do not change a teacher."""
        return GroupKey(
            self.reward,
            self.observe_reference,
            self.curriculum,
            self.teacher_budget,
            None,
            self.compute,
            "",
            "",
            "",
        )

    def text(self) -> str:
        return ", ".join(f"{f.name}={getattr(self, f.name)}" for f in fields(self))


def group_runs(
    runs: list[Run], allow_duplicates: bool = False, notes: list[str] | None = None
) -> dict[GroupKey, list[Run]]:
    """Runs by :class:`GroupKey`, each group's runs in seed order. A second run with the same
    key and seed raises :class:`DuplicateRunsError` naming both, unless ``allow_duplicates``:
    then the newest (its files' modification time) is kept and the others named in ``notes``."""
    notes = [] if notes is None else notes
    by_key: dict[GroupKey, dict[object, list[Run]]] = {}
    for run in runs:
        by_key.setdefault(GroupKey.of(run), {}).setdefault(run.seed, []).append(run)
    out: dict[GroupKey, list[Run]] = {}
    for key, seeds in by_key.items():
        kept = []
        for seed, same in seeds.items():
            if len(same) > 1:
                names = ", ".join(r.label for r in same)
                if not allow_duplicates:
                    raise DuplicateRunsError(
                        f"runs {names} are the same experiment (seed {seed}; {key.text()}): "
                        "pooling them counts a seed twice; remove one, or pass "
                        "--allow-duplicates to keep the newest"
                    )
                newest = max(same, key=lambda r: r.mtime)
                dropped = ", ".join(r.label for r in same if r is not newest)
                notes.append(
                    f"--allow-duplicates: seed {seed} of {key.reward}/{key.variant} has "
                    f"{len(same)} runs; kept the newest, {newest.label}; left out {dropped}"
                )
                same = [newest]
            kept += same
        out[key] = sorted(kept, key=lambda r: (str(r.seed), r.label))
    return out


def _arm_defaults(reward: str, conf_dir: Path) -> dict:
    """conf/experiment/<reward>.yaml's curriculum and budget scale (the paper's pairing), if any."""
    path = conf_dir / "experiment" / f"{reward}.yaml"
    if not path.is_file():
        return {}
    try:
        data = OmegaConf.to_container(OmegaConf.load(path), resolve=False) or {}
    except Exception:  # noqa: BLE001 - a broken option file must not stop the figures
        return {}
    out: dict = {}
    for item in data.get("defaults", []) or []:
        if isinstance(item, dict):
            for k, v in item.items():
                if str(k).split()[-1].strip("/") == "curriculum":
                    out["curriculum"] = str(v)
    scale = (data.get("teacher") or {}).get("budget_scale")
    if scale is not None:
        out["budget_scale"] = float(scale)
    return out


DIFF_FIELDS = (
    ("curriculum", lambda k: str(k.curriculum)),
    ("teacher_budget", lambda k: f"{k.teacher_budget} it"),
    ("observe_reference", lambda k: "+ref obs" if k.observe_reference else "no ref obs"),
    ("distill_budget", lambda k: f"distill {k.distill_budget} it"),
    ("compute", lambda k: str(k.compute)),
    ("stage", lambda k: f"stage {k.stage}"),
    ("variant", lambda k: str(k.variant)),
    ("checkpoints", lambda k: "from " + (Path(k.checkpoints).parent.parent.name or "scratch")),
)


def series_names(keys: list[GroupKey], by: str) -> dict[GroupKey, str]:
    """A readable, unique name per group among ``keys``: the ``by`` field (``reward`` or
    ``variant``), then in brackets what differs between groups sharing it. By reward, the group
    that stands for the arm in the paper's comparison (:func:`primary`) keeps the plain name
    (and the arm's colour); the others, controls, carry the brackets."""
    out: dict[GroupKey, str] = {}
    base = {k: str(getattr(k, by)) for k in keys}
    for name in set(base.values()):
        same = [k for k in keys if base[k] == name]
        parts = []
        for field_name, show in DIFF_FIELDS:
            if field_name == by:
                continue
            if len({getattr(k, field_name) for k in same}) > 1:
                parts.append(show)
        plain = primary(same, name) if by == "reward" and len(same) > 1 else None
        for k in same:
            text = ", ".join(show(k) for show in parts)
            out[k] = f"{name} [{text}]" if text and k != plain else name
    return out


def primary(keys: list[GroupKey], reward: str, conf_dir: Path = CONF_DIR) -> GroupKey | None:
    """The group that stands for ``reward`` in the paper's comparison: the one configured as
    ``conf/experiment/<reward>.yaml`` says (curriculum, budget scale; no extra observation) if exactly
    one is, else the only group of that reward, else None (ambiguous: the caller says so)."""
    mine = [k for k in keys if k.reward == reward]
    if len({k.stage for k in mine}) > 1:  # a student of its own teacher over a fixed one's
        mine = [k for k in mine if k.stage == "all"] or mine
    if len(mine) <= 1:
        return mine[0] if mine else None
    arm = _arm_defaults(reward, conf_dir)
    budgets = sorted({k.teacher_budget for k in mine if isinstance(k.teacher_budget, int)})
    match = []
    for k in mine:
        if k.observe_reference:
            continue
        if "curriculum" in arm and k.curriculum != arm["curriculum"]:
            continue
        if arm.get("budget_scale", 1.0) > 1.0 and budgets and k.teacher_budget != budgets[-1]:
            continue
        match.append(k)
    return match[0] if len(match) == 1 else None
