"""``resume=<run dir>`` with other overrides: the safe ones apply, the others are refused.

A resumed run continues with its own ``config.yaml`` (its sizes, seed and policy), not with
today's defaults. An override given along with ``resume=`` is

- ignored when it sets the value the run already has (the same command line run again);
- applied, and written into the run's config.yaml, when it is in :data:`RESUME_SAFE`: values
  that change how long the run goes on, how often it saves and evaluates, and where it logs,
  not what it learns or how it is measured;
- otherwise refused, with one line naming every such override, before any simulation.

Nothing is dropped silently. ``hydra.*`` overrides configure Hydra itself and pass through.

Pure data: no simulator import.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, is_dataclass, replace
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from march.config import ConfigError, MarchConfig, to_march_config
from march.config.terms import import_extra_modules
from march.store.file_config import check_named_modules, interpolations

MAX_CONFIG_BYTES = 1 << 20
"""A run's config.yaml is ~10 KB; a larger one is not a file march wrote."""

RESUME_SAFE = (
    "teacher.max_iterations",  # more iterations (never fewer than the run was started with)
    "distill.max_iterations",
    "teacher.save_interval",
    "teacher.eval_interval",
    "distill.save_interval",
    "distill.eval_interval",
    "teacher.max_nonfinite_updates",
    "distill.max_nonfinite_updates",
    "compute.torch_threads",  # speed only
    "compute.dist_timeout_s",  # how long a rank waits for the others
    "compute.compile_math",  # speed only (agrees with eager within 1e-4)
    "compute.compile_mode",  # speed only (the same compiled maths, replayed as CUDA graphs)
    "figures",  # what the figures compare: labels only
    "compute.device",  # where it runs: every saved state is carried to the new device
    "logger",  # every logger.* field and the logger=<choice> group
)
"""Config paths (a section: every field in it) an override may change on resume."""

GROUP_FIELDS = {
    # A config-group choice (conf/<group>/*.yaml) names the run by these fields: the same choice
    # as the run's is a no-op, another one is refused (it would change more than its name).
    "compute": ("compute.name",),
    "reward": ("reward.name",),
    "student": ("student.variant",),
    "curriculum": ("curriculum.name",),
    "dr": ("dr.name",),
    "experiment": ("reward.name", "curriculum.name"),
    "arm": ("reward.name", "curriculum.name"),  # conf/experiment/'s old name, in older runs
}
GROWING = ("teacher.max_iterations", "distill.max_iterations")
"""Safe only upwards: a run cannot un-train the iterations its checkpoints hold."""


def _get(obj: Any, path: str) -> Any:
    for part in path.split("."):
        obj = getattr(obj, part)
    return obj


def _safe(path: str) -> bool:
    return any(path == s or path.startswith(s + ".") for s in RESUME_SAFE)


def _unreadable(run_dir: Path, option: str, err: BaseException) -> ConfigError:
    first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
    return ConfigError(f"{option}={run_dir}: its config.yaml cannot be read ({first})")


def saved_config_text(run_dir: Path, option: str = "resume") -> str:
    """The run's config.yaml as text through the gate: no link, bounded, no anchor, alias or
    tag (a billion-laughs file, judged on the parser's events, never expanded); one
    :class:`ConfigError` line. Needs no torch: ``march.train`` reads it before a config is
    composed (compute=auto asks torch for CUDA), so a crafted file is refused in ~50 MB."""
    from march.store.bounded_read import FileRefused, read_yaml_text

    path = run_dir / "config.yaml"
    try:
        return read_yaml_text(path, f"{option}={run_dir}: {path}", MAX_CONFIG_BYTES, "a run")
    except FileRefused as err:
        raise ConfigError(str(err)) from None
    except Exception as err:  # noqa: BLE001 - any unreadable file is the same user error
        raise _unreadable(run_dir, option, err) from None


def load_saved_config(
    run_dir: Path, option: str = "resume", named: Sequence[str] | None = None
) -> MarchConfig:
    """The run's config.yaml, validated. A value holding an interpolation or a resolver call
    (``${...}``, ``${oc.env:...}``, ``${oc.decode:...}``, however the YAML spells it: escapes
    such as ``"\\x24{"`` are decoded by the parser first) is refused, naming its key, and
    nothing is resolved: march never writes one. ``named``: the modules the user named (their
    ``extra_modules``); a module the file names and they did not is refused, never imported."""
    path = run_dir / "config.yaml"
    text = saved_config_text(run_dir, option)
    try:
        raw = OmegaConf.create(text)
        # Unresolved: the strings exactly as parsed, interpolations and all.
        tree = OmegaConf.to_container(raw, resolve=False)
        bad = interpolations(tree)
    except Exception as err:  # noqa: BLE001 - any unreadable file is the same user error
        raise _unreadable(run_dir, option, err) from None
    if bad:
        raise ConfigError(
            f"{option}={run_dir}: {path} key {bad[0]} holds a '${{...}}' interpolation or resolver"
            f"{f' (and {len(bad) - 1} more key(s))' if len(bad) > 1 else ''}, which march never "
            "writes; refusing to resolve a modified config (restore the file or start a new run)"
        )
    if named is not None and isinstance(tree, dict):
        check_named_modules(tree.get("extra_modules"), named, f"{option}={run_dir}: {path}")
        import_extra_modules(tree.get("extra_modules") or [])  # the user named each one
    try:
        return to_march_config(OmegaConf.merge(OmegaConf.structured(MarchConfig), raw))
    except ConfigError as err:
        raise ConfigError(f"{option}={run_dir}: its config.yaml is not valid: {err}") from None
    except Exception as err:  # noqa: BLE001 - any unreadable file is the same user error
        raise _unreadable(run_dir, option, err) from None


def check_device(run_dir: Path, saved: MarchConfig, cfg: MarchConfig) -> None:
    """A run saved on CUDA, resumed where there is none, needs ``compute.device=<dev>``: said in
    one line before any env is built (not torch's assertion from inside the env)."""
    from march.config.cli import cuda_available

    dev = cfg.compute.device
    if dev.startswith("cuda") and not cuda_available():
        how = (
            f"the run was saved on {saved.compute.device}"
            if dev == saved.compute.device
            else f"compute.device={dev} was asked for"
        )
        raise ConfigError(
            f"resume={run_dir}: {how} and CUDA is not available on this machine; resume it on "
            f"the CPU with: resume={run_dir} compute.device=cpu"
        )


def _parse(overrides: Sequence[str]) -> list[tuple[str, str]]:
    from hydra.core.override_parser.overrides_parser import OverridesParser

    return [
        (ov.key_or_group, ov.input_line or ov.key_or_group)
        for ov in OverridesParser.create().parse_overrides(list(overrides))
    ]


def resume_config(
    run_dir: Path, composed: MarchConfig, overrides: Sequence[str]
) -> tuple[MarchConfig, list[str]]:
    """The config a resumed run continues with, and one line per override it applied.

    ``composed``: the config Hydra composed from the command line (``overrides``, as typed:
    ``HydraConfig.get().overrides.task``). Raises :class:`ConfigError` naming every override
    that cannot change on resume.
    """
    saved = load_saved_config(run_dir, named=composed.extra_modules)
    changes: dict[str, Any] = {}
    refused: list[str] = []
    for key, text in _parse(overrides):
        key = key.lstrip("+~")
        if key == "resume" or key.startswith("hydra"):
            continue
        if key == "logger" or key.startswith("logger."):
            changes["logger"] = composed.logger
            continue
        paths = GROUP_FIELDS.get(key, (key,))
        try:
            same = all(_get(composed, p) == _get(saved, p) for p in paths)
        except AttributeError:
            refused.append(text)  # e.g. +sweep=...: not a value of the run
            continue
        if same:
            continue
        if len(paths) == 1 and _safe(paths[0]):
            changes[paths[0]] = _get(composed, paths[0])
        else:
            refused.append(text)
    if refused:
        raise ConfigError(
            f"resume={run_dir}: {', '.join(refused)} cannot change on resume (the run goes on "
            f"with its config.yaml); only {', '.join(RESUME_SAFE)} can. Drop "
            f"{'it' if len(refused) == 1 else 'them'}, or start a new run"
        )
    check_changes(run_dir, saved, changes, "resume")
    notes = []
    sections: dict[str, dict[str, Any]] = {}
    for path, value in changes.items():
        section, _, name = path.partition(".")
        if name:
            sections.setdefault(section, {})[name] = value
            notes.append(f"[resume] {path}: {_get(saved, path)} -> {value}")
        elif value != _get(saved, section):
            sections[section] = value
            notes.append(f"[resume] {section}: {_get(saved, section)} -> {value}")
    new = {
        s: v if not isinstance(v, dict) else replace(getattr(saved, s), **v)
        for s, v in sections.items()
    }
    cfg = replace(saved, resume=composed.resume, **new)
    check_device(run_dir, saved, cfg)
    return cfg, notes


def _leaves(node: Any, prefix: str = "") -> dict[str, Any]:
    """Dotted path -> value of every leaf of a dataclass / dict tree."""
    if is_dataclass(node) and not isinstance(node, type):
        node = asdict(node)
    if not isinstance(node, dict):
        return {prefix: node}
    out: dict[str, Any] = {}
    for k, v in node.items():
        out.update(_leaves(v, f"{prefix}.{k}" if prefix else str(k)))
    return out


def config_differences(saved: MarchConfig, new: MarchConfig) -> tuple[list[str], list[str]]:
    """(unsafe, safe) differences between two configs, each ``key: saved -> new``."""
    a, b = _leaves(saved), _leaves(new)
    unsafe, safe = [], []
    for key in sorted(set(a) | set(b)):
        if key == "resume" or a.get(key) == b.get(key):
            continue
        text = f"{key}: {a.get(key)!r} -> {b.get(key)!r}"
        (safe if _safe(key) else unsafe).append(text)
    return unsafe, safe


def _listed(items: list[str], most: int = 6) -> str:
    more = f" (and {len(items) - most} more)" if len(items) > most else ""
    return "; ".join(items[:most]) + more


def adopt_config(run_dir: Path, composed: MarchConfig) -> tuple[MarchConfig, list[str]]:
    """A new run started in ``run_dir``, which already holds a run (its config.yaml): the same
    rule as ``resume=`` (:func:`check_changes`). The identical config (the same command run
    again, a Slurm requeue) continues the run; differences in :data:`RESUME_SAFE` apply
    (iterations only upwards, the teacher's not once the distillation has started); any other
    difference is refused in one line naming the keys, before anything is written."""
    saved = load_saved_config(run_dir, "hydra.run.dir", named=composed.extra_modules)
    unsafe, safe = config_differences(saved, composed)
    if unsafe:
        raise ConfigError(
            f"hydra.run.dir={run_dir} already holds a run with another config ({_listed(unsafe)})"
            f"; a new run does not take over another run's directory: continue that run with "
            f"resume={run_dir}, or give this one its own hydra.run.dir"
        )
    changes = {p: _get(composed, p) for p in GROWING if _get(composed, p) != _get(saved, p)}
    check_changes(run_dir, saved, changes, "hydra.run.dir")
    notes = [f"[run dir] {run_dir} holds this run: continuing it"]
    notes += [f"[run dir] {d}" for d in safe]
    check_device(run_dir, saved, composed)
    return composed, notes


def check_changes(run_dir: Path, saved: MarchConfig, changes: dict[str, Any], option: str) -> None:
    """The rules on a run's safe changes, one copy for ``resume=`` and for a new run in the
    run's directory (``option``: ``resume`` | ``hydra.run.dir``): iteration counts only grow,
    and the teacher's is fixed once ``student/`` holds a checkpoint (a student of that
    teacher). ``changes``: dotted path -> new value, only the values that differ."""
    for path in GROWING:
        if path in changes and changes[path] < _get(saved, path):
            raise ConfigError(
                f"{option}={run_dir}: {path}={changes[path]} is below the run's "
                f"{_get(saved, path)}; a run's iterations can only be added"
            )
    if "teacher.max_iterations" in changes and any((run_dir / "student").glob("*.pt")):
        raise ConfigError(
            f"{option}={run_dir}: teacher.max_iterations cannot change once the distillation has "
            "started (student/ holds checkpoints of a student of the current teacher)"
        )
