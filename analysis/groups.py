"""Which runs may be pooled and compared: the group key, duplicate seeds, the series names.

The unit of replication is the seed (a training run). Runs are pooled into one point only when
everything that defines the experiment is equal. The key is DERIVED from the run's whole resolved
``config.yaml``: every value except those listed in :data:`MAY_VARY` (the seed, output and
resume paths, logging, presentation, where and how fast the same numbers are computed). A new
option therefore separates groups by itself; nothing has to be added here for it. The readable
fields of :class:`GroupKey` (reward, variant, curriculum, budgets, compute, stage, checkpoints)
name groups; ``config`` holds the rest.

Two runs with the same key and seed are the same experiment twice (a killed duplicate, a re-run
in another folder): pooling them would count a seed twice, so :func:`group_runs` refuses them in
one line naming the runs, or, asked to (``--allow-duplicates``), keeps the newest and says so.

Comparisons (:func:`differences`, :func:`arm_fields`): two groups may be compared for a claim
only if they differ in the compared arms' own fields and nothing else. An arm's own fields are
what its ``conf/experiment/<arm>.yaml`` chooses (the option groups it overrides, e.g.
``reward.*`` and ``curriculum.*``, and the keys it sets, e.g. ``teacher.budget_scale``); for the
ablation, ``student.*``. The paper's arm is the group whose values agree with those files
(:func:`primary`).

Series names: a group is named by its reward arm, followed in brackets by what tells it apart
from the other groups of the same arm in the same figure (``modelfree [stones, 2 it]``,
``clf [eval.pushes=false]``); a group that is not the paper's arm of its reward, a plugin term in
its reward for instance, is named a variant with what differs (``clf [variant:
reward.terms.swing_clearance.weight=0.5]``), even when it is the only group of that reward.
Reads files, and the typed config's defaults (march.config) for what an option file leaves
unset.

:func:`unlike` is the one like-for-like rule: every output that compares or draws groups side by
side (claims, final metrics, sample efficiency, stdout, figures) asks it, and writes a refused
pair as :func:`not_compared`.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from pathlib import Path

from omegaconf import OmegaConf

from analysis.rundirs import Run, flatten, norm

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"

MAY_VARY = (
    "seed",
    "resume",
    "out",
    "objective",
    "logger.",
    "figures.",
    "compute.device",
    "compute.torch_threads",
    "compute.dist_timeout_s",
    "compute.compile_math",
    "compute.compile_mode",
    "teacher.save_interval",
    "distill.save_interval",
    "reward.label",
    "reward.color",
    "reward.order",
    "student.label",
    "student.color",
    "student.order",
)
"""Config keys (a trailing dot: a whole section) that may differ between the seeds of one group:
the seed itself; where files go (``out``, ``resume``) and how often checkpoints are written;
what is logged and drawn (``logger``, ``figures``, labels and colours); what a sweeper optimises
(``objective``); and where and how fast the same numbers are computed (the device, threads, the
process group's timeout, ``torch.compile`` of the same maths). Everything else is the
experiment: ``compute.eval_num_envs`` included, because an evaluation's rows depend on its wave
size in their last bits: every random number is keyed by rollout (march.env.rollout_draws), but
mujoco_warp's contact solve is not batch-invariant and a fall amplifies it (docs/scaling.md)."""

NAMED = {
    "reward": "reward.name",
    "variant": "student.variant",
    "curriculum": "curriculum.name",
    "compute": "compute.name",
    "stage": "stage",
    "teacher_budget": "teacher.budget",
    "distill_budget": "distill.max_iterations",
    "observe_reference": "reward.observe_reference",
    "checkpoints": "teacher_ckpt|student_ckpt",
}
"""The readable key fields and the config key each stands for (``teacher.budget``:
teacher.max_iterations x teacher.budget_scale)."""


def may_vary(key: str) -> bool:
    return any(key == p or (p.endswith(".") and key.startswith(p)) for p in MAY_VARY)


class DuplicateRunsError(ValueError):
    """Two runs of one group share a seed (the message is the one line to print)."""


TEACHER_ONLY = ("stage", "student.", "distill.", "student_ckpt", "eval.policy")
"""What does not change a teacher: its students, their distillation, the stage it ran in."""


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
    config: tuple[tuple[str, str], ...] = ()  # the rest of the resolved config (MAY_VARY out)

    @classmethod
    def of(cls, run: Run) -> GroupKey:
        config = tuple(sorted((k, v) for k, v in run.config.items() if not may_vary(k)))
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
            config=config,
        )

    def view(self) -> dict[str, str]:
        """Every value of the key by config key: the config, and the named fields under
        :data:`NAMED`'s keys (runs built without a config.yaml have only those)."""
        out = dict(self.config)
        for name, key in NAMED.items():
            value = getattr(self, name)
            out[key] = norm(value if value != "" else None)
        return out

    def without(self, prefixes: tuple[str, ...], **named) -> GroupKey:
        """This key with the config keys under ``prefixes`` dropped and ``named`` fields set."""
        config = tuple(
            (k, v)
            for k, v in self.config
            if not any(k == p or (p.endswith(".") and k.startswith(p)) for p in prefixes)
        )
        return replace(self, config=config, **named)

    def teacher_part(self) -> GroupKey:
        """The key of the teacher alone: variant and distillation do not change a teacher."""
        return self.without(TEACHER_ONLY, distill_budget=None, variant="", stage="", checkpoints="")

    def arm_part(self) -> GroupKey:
        """The key without the student variant's fields (the arm a variant belongs to)."""
        return self.without(("student.",), variant="")

    def text(self) -> str:
        named = ", ".join(f"{f.name}={getattr(self, f.name)}" for f in fields(self)[:-1])
        return named + (f" and {len(self.config)} more config values" if self.config else "")


def differences(a: GroupKey, b: GroupKey) -> list[str]:
    """The config keys (dotted) where two groups differ, a key one of them lacks included."""
    va, vb = a.view(), b.view()
    return sorted(k for k in va.keys() | vb.keys() if va.get(k, "unset") != vb.get(k, "unset"))


def owned(key: str, own: tuple[str, ...]) -> bool:
    """Whether config ``key`` is one of ``own`` (a trailing dot: a whole section)."""
    return any(key == f or (f.endswith(".") and key.startswith(f)) for f in own)


def foreign(a: GroupKey, b: GroupKey, own: tuple[str, ...]) -> list[str]:
    """Where ``a`` and ``b`` differ outside ``own``: empty when they may be compared."""
    return [k for k in differences(a, b) if not owned(k, own)]


def shorten(keys: list[str], most: int = 6) -> str:
    text = ", ".join(keys[:most])
    return text + (f" and {len(keys) - most} more" if len(keys) > most else "")


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


def _yaml(path: Path) -> dict:
    if not path.is_file():
        return {}
    try:
        data = OmegaConf.to_container(OmegaConf.load(path), resolve=False) or {}
    except Exception:  # noqa: BLE001 - a broken option file must not stop the figures
        return {}
    return data if isinstance(data, dict) else {}


def _experiment(arm: str, conf_dir: Path) -> tuple[dict[str, str], dict]:
    """conf/experiment/<arm>.yaml: ({option group: option} it overrides, its own keys)."""
    data = _yaml(conf_dir / "experiment" / f"{arm}.yaml")
    groups: dict[str, str] = {}
    for item in data.get("defaults", []) or []:
        if isinstance(item, dict):
            for k, v in item.items():
                groups[str(k).split()[-1].strip("/")] = str(v)
    return groups, {k: v for k, v in data.items() if k != "defaults"}


def arm_fields(arm: str, conf_dir: Path = CONF_DIR) -> tuple[str, ...]:
    """The config keys ``arm`` chooses (a trailing dot: a whole section): the option groups and
    keys of ``conf/experiment/<arm>.yaml``; ``reward.`` alone for an arm without one."""
    groups, own = _experiment(arm, conf_dir)
    out = {f"{g}." for g in groups} | set(flatten(own)) | {"reward."}
    if "teacher.budget_scale" in out:
        out.add("teacher.budget")  # teacher.max_iterations x teacher.budget_scale
    return tuple(sorted(out))


def _schema_defaults() -> dict:
    """Every section's defaults as the typed config declares them (march.config), before any
    option file: what an option file leaves unset is these values."""
    global _DEFAULTS
    if _DEFAULTS is None:
        from march.config.schema import MarchConfig

        _DEFAULTS = OmegaConf.to_container(OmegaConf.structured(MarchConfig), resolve=False)
    return _DEFAULTS


_DEFAULTS: dict | None = None


def _terms_canonical(spec: dict[str, str]) -> dict[str, str]:
    """A reward term written as a weight (``reward.terms.clf: 10``) and as a mapping
    (``{weight: 10, params: {}}``) are the same term: both become ``reward.terms.clf.weight``
    (an empty ``params`` dropped)."""
    out = {}
    for k, v in spec.items():
        parts = k.split(".")
        if k.startswith("reward.terms.") and len(parts) == 3:
            k = f"{k}.weight"
        if k.startswith("reward.terms.") and k.endswith(".params") and v == "{}":
            continue
        out[k] = v
    return out


def arm_spec(arm: str, conf_dir: Path = CONF_DIR) -> dict[str, str]:
    """What the paper's ``arm`` is, as a whole: every value of the sections its experiment file
    chooses (the typed config's defaults with ``conf/<group>/<option>.yaml`` over them:
    ``conf/reward/clf.yaml``'s terms and weights and every other reward and curriculum
    setting) and the keys the experiment file sets itself, by config key (names, labels and
    colours left out). Without an experiment file, ``conf/reward/<arm>.yaml``; nothing for an
    arm without either (a name no file defines)."""
    groups, own = _experiment(arm, conf_dir)
    if not groups and not own:
        groups = {"reward": arm}
    spec: dict[str, str] = {}
    for group, option in groups.items():
        data = _yaml(conf_dir / group / f"{option}.yaml")
        if not data:
            continue
        base = _schema_defaults().get(group)
        if isinstance(base, dict):
            data = OmegaConf.to_container(OmegaConf.merge(base, data), resolve=False)
        spec.update({f"{group}.{k}": v for k, v in flatten(data).items()})
    spec.update(flatten(own))
    return _terms_canonical({k: v for k, v in spec.items() if not may_vary(k)})


def spec_mismatch(key: GroupKey, arm: str, conf_dir: Path = CONF_DIR) -> list[str]:
    """Why a group is not the paper's ``arm`` (empty: it is): ``key=value`` where it disagrees
    with :func:`arm_spec`, and every key of the arm's own sections (:func:`arm_fields`: the
    reward, the curriculum, ...) that the arm's config does not have at all, e.g. a plugin
    reward term and its parameters (``reward.terms.swing_clearance.weight=0.5 (beyond the
    arm's config)``): the arm is its config as a whole, not only the keys its YAML names. A key
    the group's config lacks (an older run) is not held against it."""
    spec = arm_spec(arm, conf_dir)
    if not spec:
        return []
    view = _terms_canonical(key.view())
    why = [
        f"{k}={view[k]} (conf: {v})"
        for k, v in spec.items()
        if k in view and view[k] != v and not (k == "reward.name" and view[k] == arm)
    ]
    own = arm_fields(arm, conf_dir)
    named = set(NAMED.values())
    why += [
        f"{k}={view[k]} (beyond the arm's config)"
        for k in sorted(view)
        if k not in spec and k not in named and owned(k, own) and not may_vary(k)
    ]
    return why


def mismatch_keys(why: list[str]) -> list[str]:
    """The ``key=value`` parts of :func:`spec_mismatch`'s lines (what a series name shows)."""
    return [w.split(" (")[0] for w in why]


# What a differing named field already says: the config keys it explains in a series name.
EXPLAINS = {
    "curriculum": ("curriculum.",),
    "teacher_budget": ("teacher.max_iterations", "teacher.budget_scale"),
    "observe_reference": ("reward.observe_reference",),
    "distill_budget": ("distill.max_iterations",),
    "stage": ("stage",),
    "variant": ("student.",),
    "checkpoints": ("teacher_ckpt", "student_ckpt"),
    "reward": ("reward.",),
}
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
MAX_NAMED_KEYS = 3


def _preset_keys(conf_dir: Path) -> tuple[str, ...]:
    """Every key a compute preset sets (conf/compute/*.yaml): a differing preset explains them."""
    keys: set[str] = set()
    for path in (conf_dir / "compute").glob("*.yaml"):
        keys |= set(flatten(_yaml(path)))
    return tuple(sorted(keys)) + ("compute.",)


def series_names(keys: list[GroupKey], by: str, conf_dir: Path = CONF_DIR) -> dict[GroupKey, str]:
    """A readable, unique name per group among ``keys``: the ``by`` field (``reward`` or
    ``variant``), then in brackets what differs between groups sharing it: the named fields
    (curriculum, budget, compute, ...), then any other config key as ``key=value`` (at most
    :data:`MAX_NAMED_KEYS`, then how many more). By reward, the group that stands for the arm in
    the paper's comparison (:func:`primary`) keeps the plain name (and the arm's colour); the
    others, controls and variations, carry the brackets."""
    out: dict[GroupKey, str] = {}
    base = {k: str(getattr(k, by)) for k in keys}
    for name in set(base.values()):
        same = [k for k in keys if base[k] == name]
        parts, explained = [], [NAMED[by]]
        for field_name, show in DIFF_FIELDS:
            if field_name == by:
                continue
            if len({getattr(k, field_name) for k in same}) > 1:
                parts.append(show)
                if field_name == "compute":
                    explained += _preset_keys(conf_dir)
                else:
                    explained += EXPLAINS.get(field_name, ())
        views = [k.view() for k in same]
        rest = sorted(
            key
            for key in set().union(*views)
            if len({v.get(key, "unset") for v in views}) > 1
            and key not in NAMED.values()
            and not owned(key, tuple(explained))
        )
        plain = primary(same, name, conf_dir) if by == "reward" and len(same) > 1 else None
        for k, view in zip(same, views, strict=True):
            shown = [show(k) for show in parts]
            extra = [f"{key}={view.get(key, 'unset')}" for key in rest]
            shown += extra[:MAX_NAMED_KEYS]
            if len(extra) > MAX_NAMED_KEYS:
                shown.append(f"+{len(extra) - MAX_NAMED_KEYS} more")
            text = ", ".join(shown)
            variant = variant_of_arm(k, conf_dir) if by == "reward" else []
            if variant and not text:  # alone, it would carry the arm's plain name
                text = shorten(mismatch_keys(variant), MAX_NAMED_KEYS)
            if variant:  # never the paper's arm, in any output (issue 57)
                text = f"variant: {text}"
            out[k] = f"{name} [{text}]" if text and k != plain else name
    return out


def variant_of_arm(key: GroupKey, conf_dir: Path = CONF_DIR) -> list[str]:
    """Why the group is not the paper's arm of its reward (empty: it is, or its reward has no
    arm in ``conf/``): :func:`spec_mismatch` against the experiment of that name, and the
    reference observation where the arm has none."""
    why = spec_mismatch(key, key.reward, conf_dir)
    if key.observe_reference and not any(w.startswith("reward.observe_reference") for w in why):
        if arm_spec(key.reward, conf_dir):
            why.append("reward.observe_reference=true")
    return why


VARIANT_FIELDS = ("student.",)
"""What the ablation's groups may differ in: the student alone."""


def unlike(a: GroupKey, b: GroupKey, by: str = "reward", conf_dir: Path = CONF_DIR) -> list[str]:
    """The one like-for-like rule every output that compares groups applies (claims.md,
    final_metrics, sample_efficiency, stdout and every figure; issue 57): the config keys where
    ``a`` and ``b`` differ outside what the comparison is about, empty when they may be
    compared. Arms (``by="reward"``): their own fields (:func:`arm_fields` of both rewards);
    student variants of one teacher (``by="variant"``): ``student.*`` only."""
    if by == "variant":
        own = VARIANT_FIELDS
    else:
        own = tuple(
            sorted(set(arm_fields(a.reward, conf_dir)) | set(arm_fields(b.reward, conf_dir)))
        )
    return foreign(a, b, own)


def not_compared(bad: list[str]) -> str:
    """How a refused pair is written everywhere: ``not compared (differ in compute.name)``."""
    return f"not compared (differ in {shorten(bad)})"


def like_for_like(
    keys: list[GroupKey], anchor: GroupKey | None, by: str = "reward", conf_dir: Path = CONF_DIR
) -> tuple[list[GroupKey], dict[GroupKey, list[str]]]:
    """Which of ``keys`` may be drawn or listed beside ``anchor`` (the group every other is
    compared with): (kept, {refused key: the keys it differs in}). No anchor: all kept."""
    if anchor is None:
        return list(keys), {}
    refused = {k: bad for k in keys if k != anchor and (bad := unlike(anchor, k, by, conf_dir))}
    return [k for k in keys if k not in refused], refused


def primary(keys: list[GroupKey], reward: str, conf_dir: Path = CONF_DIR) -> GroupKey | None:
    """The group that stands for ``reward`` in the paper's comparison: among the groups of that
    reward (students of their own teacher first), the one whose values agree with
    ``conf/experiment/<reward>.yaml`` and the options it chooses (:func:`spec_mismatch`; no
    extra observation); the only group of that reward if there is one and it is the arm
    (:func:`variant_of_arm` empty); else None (ambiguous, or only variants: the caller says
    so)."""
    mine = [k for k in keys if k.reward == reward]
    if len({k.stage for k in mine}) > 1:  # a student of its own teacher over a fixed one's
        mine = [k for k in mine if k.stage == "all"] or mine
    if len(mine) <= 1:  # a lone group stands for the arm only if it is the arm (issue 57)
        return mine[0] if mine and not variant_of_arm(mine[0], conf_dir) else None
    budgets = sorted({k.teacher_budget for k in mine if isinstance(k.teacher_budget, int)})
    scale = _experiment(reward, conf_dir)[1].get("teacher", {}) or {}
    match = []
    for k in mine:
        if variant_of_arm(k, conf_dir):
            continue
        # Runs without teacher.budget_scale in their config: the larger budget is the 2x arm.
        if float(scale.get("budget_scale", 1.0)) > 1.0 and "teacher.budget_scale" not in dict(
            k.config
        ):
            if budgets and k.teacher_budget != budgets[-1]:
                continue
        match.append(k)
    return match[0] if len(match) == 1 else None
