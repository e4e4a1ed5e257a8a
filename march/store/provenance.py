"""A checkpoint defines its policy: the config a checkpoint was trained with wins over today's.

``stage=eval``, ``march.play``, ``march.export`` and ``stage=student`` (the teacher's reward set)
read a checkpoint (through :func:`march.store.gate.policy_from_checkpoint`) that carries the config it was trained with (``payload["config"]``, written with
``dataclasses.asdict(cfg)``). :func:`apply_checkpoint_config` takes from it everything that defines
the policy - the reward set, the student variant and its network, the observation layout - and
returns the config to run with; the evaluation protocol (``eval.*``, ``compute.*``, ``seed``,
``dr``, course geometry, terminations) stays the user's. A policy-defining value the user chose
explicitly on the command line that disagrees with the checkpoint is a one-line
:class:`~march.config.ConfigError` naming both values, raised before any simulation.

Pure data: no simulator import.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import asdict, fields, is_dataclass, replace
from typing import Any

from march.config import ConfigError, MarchConfig
from march.store.file_config import check_named_modules

# What defines a policy, by the dotted path of its config field. A path naming a section takes
# every field of that section.
COMMON_FIELDS = (
    "reward.name",  # the reward set decides the observation layout (clf adds the reference) and
    "reward.terms",  # the return a rollout is scored with; the figures label runs by it
    "reward.label",  # how the figures draw the arm (march.config.registry)
    "reward.color",
    "reward.order",
    "env.history_length",  # proprioception history [control steps] the networks read
    "env.sim_dt",  # control rate = 1 / (sim_dt * decimation): a policy is trained at one rate
    "env.decimation",
)
TEACHER_FIELDS = (
    # The actor is rebuilt from payload["ppo"]; these keep the written config.yaml truthful.
    "teacher.hidden_dims",
    "teacher.activation",
)
STUDENT_FIELDS = (
    "student",  # variant and every network size
    # The camera the student was trained to read (its corruption levels stay the protocol's).
    "depth.name",
    "depth.width",
    "depth.height",
    "depth.fovy",
    "depth.min_range",
    "depth.max_range",
    "depth.pos",
    "depth.pitch_deg",
    "depth.geom_groups",
)
LABEL_FIELDS = (
    # Labels only (the eval env always uses the stone courses): figures group runs by these.
    "curriculum.name",
    "curriculum.flat_levels",
)
GROUP_CHOICES = {
    # A config-group choice on the command line names these fields (conf/<group>/*.yaml).
    "reward": ("reward.name",),
    "student": ("student.variant",),
    "curriculum": ("curriculum.name",),
    "experiment": ("reward.name", "curriculum.name"),
    "arm": ("reward.name", "curriculum.name"),  # conf/experiment/'s old name, in older runs
}


def policy_fields(kind: str, distill: bool = False) -> tuple[str, ...]:
    """The dotted config paths a ``kind`` (teacher | student) checkpoint decides.

    ``distill``: the checkpoint is the teacher of a new distillation run (stage=student); the run's
    curriculum is then its own, not a label copied from the teacher.
    """
    if kind not in ("teacher", "student"):
        raise ValueError(f"kind={kind!r}: teacher or student")
    out = COMMON_FIELDS + (TEACHER_FIELDS if kind == "teacher" else STUDENT_FIELDS)
    return out if distill else out + LABEL_FIELDS


def explicit_paths(overrides: Sequence[str]) -> list[tuple[str, str]]:
    """(dotted config path, override as typed) for each value the command line sets explicitly.

    Group choices (``reward=clf``, ``+experiment=modelfree``) map to the fields they name; ``hydra.*``,
    deletions and sweeps are not choices of a value.
    """
    from hydra.core.override_parser.overrides_parser import OverridesParser

    out: list[tuple[str, str]] = []
    for ov in OverridesParser.create().parse_overrides(list(overrides)):
        key = ov.key_or_group
        if ov.is_delete() or key.startswith("hydra") or key.split("/")[0] == "sweep":
            continue
        text = ov.input_line or key
        if key in GROUP_CHOICES and isinstance(ov.value(), str):
            out += [(path, text) for path in GROUP_CHOICES[key]]
        else:
            out.append((key, text))
    return out


_MISSING = object()


def _get(tree: Any, path: str) -> Any:
    node = tree
    for part in path.split("."):
        if is_dataclass(node):
            node = getattr(node, part, _MISSING)
        elif isinstance(node, dict):
            node = node.get(part, _MISSING)
        else:
            return _MISSING
        if node is _MISSING:
            return _MISSING
    return node


def _plain(value: Any) -> Any:
    """Comparable form: dataclasses -> dicts, tuples -> lists, ints that are floats -> floats."""
    if is_dataclass(value) and not isinstance(value, type):
        value = asdict(value)
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, bool):
        return value
    if isinstance(value, int):
        return float(value)
    return value


def _show(value: Any) -> str:
    value = _plain(value)
    if isinstance(value, float) and value.is_integer():
        return str(int(value))
    if isinstance(value, list):
        return "[" + ",".join(_show(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ",".join(f"{k}:{_show(v)}" for k, v in value.items()) + "}"
    return str(value)


def _leaves(path: str, value: Any) -> Iterator[str]:
    """``path`` and, for a section, every field path below it."""
    if is_dataclass(value) and not isinstance(value, type):
        for f in fields(value):
            yield f"{path}.{f.name}"
    else:
        yield path


def _as_field(current: Any, saved: Any) -> Any:
    """The saved value in the type of the current field (tuples stay tuples, dicts are copied)."""
    if isinstance(current, tuple) and isinstance(saved, (list, tuple)):
        return tuple(saved)
    if isinstance(current, dict) and isinstance(saved, dict):
        return dict(saved)
    if isinstance(current, float) and isinstance(saved, int) and not isinstance(saved, bool):
        return float(saved)
    return saved


def apply_checkpoint_config(
    cfg: MarchConfig,
    payload: dict[str, Any],
    explicit_overrides: Sequence[str],
    path: str,
    kind: str,
    *,
    distill: bool = False,
) -> MarchConfig:
    """``cfg`` with the policy-defining fields of the checkpoint's saved config.

    ``explicit_overrides``: the command line's overrides as typed (Hydra's
    ``HydraConfig.get().overrides.task``, or a tool's ``key=value`` arguments). One that sets a
    policy-defining field to a value other than the checkpoint's raises :class:`ConfigError`
    naming both. Fields the checkpoint's config lacks (an older schema) keep ``cfg``'s value.
    ``distill``: see :func:`policy_fields`.
    """
    saved = payload.get("config") if isinstance(payload, dict) else None
    if not isinstance(saved, dict):
        raise ConfigError(
            f"{kind}_ckpt={path} carries no saved config, so it cannot say which policy it is; "
            "use a checkpoint written by march.train"
        )
    # A module its run named (a student part or term of theirs) is never imported because the
    # file names it: the user must name it too (and then the tool has imported it already).
    check_named_modules(saved.get("extra_modules"), cfg.extra_modules, f"{kind}_ckpt={path}")
    wanted = policy_fields(kind, distill)
    leaves = [leaf for f in wanted for leaf in _leaves(f, _get(cfg, f))]
    # 1. A conflicting explicit choice is an error, before anything is changed.
    for opath, text in explicit_paths(explicit_overrides):
        for leaf in leaves:
            if opath == leaf or opath.startswith(leaf + "."):
                probe = opath
            elif leaf.startswith(opath + "."):
                probe = leaf
            else:
                continue
            mine, theirs = _get(cfg, probe), _get(saved, probe)
            if theirs is _MISSING and _get(saved, leaf) is not _MISSING:
                probe, mine, theirs = leaf, _get(cfg, leaf), _get(saved, leaf)  # e.g. a term
            if theirs is _MISSING or mine is _MISSING or _plain(mine) == _plain(theirs):
                continue
            raise ConfigError(
                f"{text} conflicts with {kind}_ckpt={path}, which was trained with "
                f"{probe}={_show(theirs)} (a checkpoint defines its policy): drop {text} from "
                f"the command line or pass a checkpoint trained with {probe}={_show(mine)}"
            )
    # 2. Take the checkpoint's values, section by section (validated by each __post_init__).
    changes: dict[str, dict[str, Any]] = {}
    for leaf in leaves:
        section, _, name = leaf.partition(".")
        theirs = _get(saved, leaf)
        if theirs is _MISSING:
            continue
        current = _get(cfg, leaf)
        changes.setdefault(section, {})[name] = _as_field(current, theirs)
    sections = {}
    try:
        for section, values in changes.items():
            sections[section] = replace(getattr(cfg, section), **values)
        return replace(cfg, **sections)
    except (TypeError, ValueError) as err:
        if isinstance(err, ConfigError):
            raise ConfigError(
                f"{kind}_ckpt={path}: its saved config is not valid here: {err}"
            ) from err
        raise ConfigError(f"{kind}_ckpt={path}: its saved config does not fit ({err})") from err


def policy_changes(before: MarchConfig, after: MarchConfig, kind: str) -> list[str]:
    """``path: old -> new`` for every policy-defining field the checkpoint changed."""
    out = []
    for f in policy_fields(kind):
        for leaf in _leaves(f, _get(before, f)):
            old, new = _get(before, leaf), _get(after, leaf)
            if _plain(old) != _plain(new):
                out.append(f"{leaf}: {_show(old)} -> {_show(new)}")
    return out
