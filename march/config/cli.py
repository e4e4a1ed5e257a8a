"""One command-line convention for every ``python -m march.<tool>``.

Every tool composes the same config tree as ``march.train`` (``conf/``) with Hydra overrides; a
tool with several jobs takes the job as its first word (``python -m march.viz terrain
out=x.png``). Tools other than ``march.train`` compose with Hydra's compose API (no output
directory, no multirun) so they stay quick.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

import hydra
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.errors import HydraException
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

import march.config  # noqa: F401  (registers the schema)
from march.config import ConfigError, MarchConfig, to_march_config
from march.config.registry import CONF_DIR
from march.config.terms import check_terms, import_extra_modules


def cuda_available() -> bool:
    import torch

    return torch.cuda.is_available()


def preset_name(name: str) -> str:
    """The compute preset ``name`` stands for on this machine: auto -> gpu or cpu, else itself."""
    if name != "auto":
        return name
    return "gpu" if cuda_available() else "cpu"


# ``${march_preset:${compute.name}}`` in conf/config.yaml names run directories after the preset
# that actually runs (``_gpu``, ``_cpu``), not ``_auto``.
OmegaConf.register_new_resolver("march_preset", preset_name, replace=True)

_UNIQUE: list[str] = []


def unique_part() -> str:
    """This process's own part of a run directory's name: its pid and 3 random bytes, in hex
    (``1a2b-9f3c01``), the same at every resolution in the process. Two runs started in the
    same second (seeds launched in a loop, nodes of one Slurm array) never share a directory."""
    if not _UNIQUE:
        import secrets

        _UNIQUE.append(f"{os.getpid():x}-{secrets.token_hex(3)}")
    return _UNIQUE[0]


# ``${march_unique:}`` in conf/config.yaml's directory templates (with ``seed${seed}``).
OmegaConf.register_new_resolver("march_unique", unique_part, replace=True)


def resolve_compute(cfg: DictConfig, overrides: Sequence[str]) -> DictConfig:
    """compute=auto -> the gpu preset when CUDA is available, else cpu.

    The chosen preset (``conf/compute/<name>.yaml``) is merged over the composed config and then
    the user's own ``key=value`` overrides are applied again, so ``compute=auto
    compute.num_envs=64`` keeps the 64.
    """
    if cfg.compute.name != "auto":
        return cfg
    chosen = preset_name("auto")
    preset = OmegaConf.load(CONF_DIR / "compute" / f"{chosen}.yaml")
    merged = OmegaConf.merge(cfg, preset)
    parsed = OverridesParser.create().parse_overrides(list(overrides))
    groups = ("reward", "student", "curriculum", "compute", "logger", "dr", "sweep", "experiment")
    for ov in parsed:
        key = ov.key_or_group
        if ov.is_delete() or key.split("/")[0] in groups or key.startswith("hydra"):
            continue  # group choices are already composed
        OmegaConf.update(merged, key, ov.value(), merge=True)
    merged.compute.name = chosen
    return merged


def compose(
    overrides: Sequence[str] = (), check_files: Callable[[DictConfig], None] | None = None
) -> DictConfig:
    """Compose conf/ with overrides (compute=auto resolved), as march.train would.
    ``check_files``: checks of the files the composed tree names, run before compute=auto is
    resolved (that asks torch for CUDA: ~250 MB resident for the import alone), so a crafted
    file is refused without torch."""
    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = hydra.compose(config_name="config", overrides=list(overrides))
    if check_files is not None:
        check_files(cfg)
    return resolve_compute(cfg, overrides)


def load(
    overrides: Sequence[str] = (), check_files: Callable[[DictConfig], None] | None = None
) -> MarchConfig:
    """The checked config; ``extra_modules`` are imported first (their student parts and terms
    register before the config's checks read the registries). ``check_files``: as
    :func:`compose`'s."""
    cfg = compose(overrides, check_files)
    import_extra_modules(OmegaConf.select(cfg, "extra_modules", default=None) or [])
    return to_march_config(cfg)


def fail(message: str, code: int = 2) -> None:
    """One clear line on stderr, then exit (no traceback: the message says how to fix it)."""
    print(f"error: {message}", file=sys.stderr)
    raise SystemExit(code)


def run_tool(
    jobs: dict[str, Callable[[MarchConfig], object]] | Callable[[MarchConfig], object],
    argv: Sequence[str] | None = None,
    usage: str = "",
    check_reward: bool = True,
    before_terms: Callable[[DictConfig], None] | None = None,
) -> object:
    """Parse ``[job] key=value ...``, compose the config and run the job with clear errors.
    ``check_reward``: check the reward terms too (imports the env's term modules; a job that
    builds no env may skip it). ``before_terms``: the tool's own checks of the files its config
    names (raising :class:`ConfigError`), run on the composed tree before compute=auto asks
    torch for CUDA and before the term check imports the simulator: a tool given a checkpoint
    passes :func:`march.store.checkpoint_file.check_checkpoint_files`, so a crafted file is one
    line in seconds, without torch (issue 59: under 200 MB resident)."""
    args = list(sys.argv[1:] if argv is None else argv)
    if callable(jobs):
        job, fn = None, jobs
    else:
        if not args or "=" in args[0]:
            fail(f"say which job: {' | '.join(jobs)} (then key=value overrides). {usage}")
        job = args.pop(0)
        if job not in jobs:
            fail(f"unknown job {job!r}; choose one of {', '.join(jobs)}")
        fn = jobs[job]
    bad = [a for a in args if "=" not in a]
    if bad:
        fail(f"expected key=value overrides, got {bad}. {usage}")
    if twice := duplicate_overrides(args) or renamed_group(args):
        fail(twice)
    try:
        cfg = load(args, before_terms)  # e.g. the checkpoint files, judged before torch loads
        if check_reward:
            check_terms(cfg)  # every term known, its params valid: before any env
    except (HydraException, OmegaConfBaseException) as err:
        if full_error():
            raise  # HYDRA_FULL_ERROR=1: the whole report, as Hydra gives it
        fail(hydra_refusal(err, args))
    except ConfigError as err:
        fail(_one_line(err))
    try:
        from march.config.memory import check_memory

        check_memory(cfg)
    except ConfigError as err:
        fail(str(err))
    if cfg.compute.torch_threads:
        import torch

        torch.set_num_threads(cfg.compute.torch_threads)
    os.environ.setdefault("WANDB_MODE", "offline")
    return fn(cfg)


RENAMED_GROUPS = {"arm": "experiment"}
"""Config groups that were renamed: old name -> new name (``conf/arm/`` became
``conf/experiment/``, 2026-12-04: it bundles a comparison arm's reward, curriculum and budget)."""


def renamed_group(args: Sequence[str]) -> str | None:
    """One line when an override chooses a renamed config group (``+arm=clf``), else None."""
    for arg in args:
        key = arg.split("=", 1)[0].lstrip("+~")
        group = key.split("/", 1)[0]
        if "=" in arg and group in RENAMED_GROUPS:
            new = RENAMED_GROUPS[group]
            value = arg.split("=", 1)[1]
            return (
                f"{arg}: the config group {group!r} is now {new!r} (conf/{new}/); "
                f"write +{new}={value}"
            )
    return None


def duplicate_overrides(args: Sequence[str]) -> str | None:
    """One line when a key is set twice on the command line (``compute.num_envs=4
    compute.num_envs=8``: Hydra silently keeps the last), else None."""
    seen: dict[str, str] = {}
    for arg in args:
        if "=" not in arg or arg.startswith("-"):
            continue
        try:
            (ov,) = OverridesParser.create().parse_overrides([arg])
        except Exception:  # noqa: BLE001 - Hydra reports a malformed override itself
            continue
        key = ov.key_or_group.lstrip("+~")
        if key in seen:
            return (
                f"{key} is set twice ({seen[key]} and {arg}); give each key once (Hydra would "
                "silently keep the last)"
            )
        seen[key] = arg
    return None


def literal_prefix(template: str) -> Path:
    """The part of a directory template before its first interpolation, up to a whole path
    component (``outputs/${now:...}/x`` -> ``outputs``): what exists before Hydra resolves it."""
    head = template.split("${", 1)[0]
    if "${" in template and not head.endswith("/"):
        head = head.rsplit("/", 1)[0] if "/" in head else ""
    return Path(head or ".")


def check_output_dir(path: str | Path, option: str) -> None:
    """``path`` can be created (or is a directory) and written: raise one line otherwise.

    The nearest existing ancestor must be a directory that takes a new entry (a probe directory
    made and removed at once: this also holds for root, for whom permission bits do not), and
    an existing ``path`` must itself be a writable directory."""
    p = Path(path)
    probe = p
    while not os.path.lexists(probe) and probe.parent != probe:
        probe = probe.parent
    if os.path.islink(probe) and not probe.exists():
        raise ConfigError(f"{option}={path}: {probe} is a broken symbolic link")
    if not probe.is_dir():
        raise ConfigError(
            f"{option}={path}: {probe} is a file, not a directory; choose another directory"
        )
    try:
        import tempfile

        os.rmdir(tempfile.mkdtemp(prefix=".march-write-probe-", dir=probe))
    except OSError as err:
        why = os.strerror(err.errno) if err.errno else str(err)
        what = "write into" if probe == p else "create directories in"
        raise ConfigError(
            f"{option}={path}: cannot {what} {probe} ({why}); choose a writable directory"
        ) from None


def _one_line(err: BaseException) -> str:
    text = str(err).strip()
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    if not lines:
        return type(err).__name__
    return lines[0] if len(lines) == 1 else f"{lines[0]} ({lines[-1]})"


HYDRA_FLAGS = ("-m", "--multirun")
"""The only Hydra flags :func:`override_problem` composes with; any other (``--cfg``,
``--config-name``, ``--info``, ...) is Hydra's own business and it reports its faults itself."""


def full_error() -> bool:
    """Whether the user asked for Hydra's whole report (``HYDRA_FULL_ERROR=1``)."""
    return os.environ.get("HYDRA_FULL_ERROR") == "1"


def _closest(word: str, choices: Sequence[str]) -> str | None:
    import difflib

    found = difflib.get_close_matches(word, list(choices), n=1, cutoff=0.5)
    return found[0] if found else None


def _typed(args: Sequence[str], key: str) -> str:
    """The override as the user typed it that sets ``key`` (a dotted key or a group)."""
    for arg in args:
        head = arg.split("=", 1)[0].lstrip("+~").split("@", 1)[0]
        if head == key:
            return arg
    return key


def hydra_refusal(err: BaseException, args: Sequence[str]) -> str:
    """One line for a Hydra / OmegaConf refusal of the overrides ``args``: the override as typed,
    what is wrong, and what would be right (the options of a group, the closest key, the type a
    key takes, how to write a list). Hydra's own report runs to 5-12 lines."""
    from hydra.errors import MissingConfigException, OverrideParseException
    from omegaconf.errors import ConfigKeyError, ValidationError

    if isinstance(err, MissingConfigException) and err.missing_cfg_file:
        group, _, name = err.missing_cfg_file.rpartition("/")
        options = list(err.options or [])
        if not group:
            return f"{_one_line(err)} (python -m march.inspect list shows every group)"
        typed = _typed(args, group)
        if not options:
            return f"{typed}: there is no config group {group!r} (conf/{group}/)"
        near = _closest(name, options)
        hint = f"; did you mean {group}={near}?" if near else ""
        return (
            f"{typed}: {group} has no option {name!r} (no {group}/{name}.yaml on the search "
            f"path); options: {', '.join(options)}{hint}"
        )
    if isinstance(err, OverrideParseException):
        typed = err.override or "an override"
        lines = str(err.message).splitlines()
        where = ""
        if len(lines) > 1 and lines[0].startswith("LexerNoViableAltException: "):
            col = len(lines[1]) - len(lines[1].lstrip()) - len("LexerNoViableAltException: ")
            if 0 <= col < len(typed):
                where = f": {typed[col]!r} (character {col + 1}) is not allowed there"
        elif lines:
            where = f" ({lines[0]})"
        return (
            f"{typed}: Hydra cannot read this override{where}; keys and plain values are ASCII "
            "letters, digits and _-./:; quote any other value (key='value')"
        )
    cause = err.__cause__ or err.__context__
    if isinstance(cause, ConfigKeyError | ValidationError) or (
        isinstance(cause, Exception) and type(cause).__name__ == "ConfigAttributeError"
    ):
        full_key = getattr(cause, "full_key", None) or getattr(cause, "key", None) or ""
        key = str(getattr(cause, "key", None) or full_key.rsplit(".", 1)[-1])
        typed = _typed(args, str(full_key)) if full_key else "an override"
        parent = getattr(cause, "parent_node", None)
        first = str(getattr(cause, "msg", "") or cause).strip().splitlines()
        first_line = first[0] if first else type(cause).__name__
        if isinstance(cause, ValidationError):
            return f"{typed}: {first_line}"
        keys: list[str] = []
        try:
            keys = [str(k) for k in parent.keys()] if parent is not None else []
        except Exception:  # noqa: BLE001 - a node without keys: no suggestion
            keys = []
        if "." not in str(full_key):
            from march.config.registry import CONF_DIR as conf

            keys += [p.name for p in conf.iterdir() if p.is_dir()]
        keys = [k for k in dict.fromkeys(keys) if k != "hydra"]
        near = _closest(key, keys)
        where = str(full_key).rsplit(".", 1)[0] if "." in str(full_key) else "the config"
        hint = f"; did you mean {near}?" if near else ""
        return (
            f"{typed}: {where} has no key {key!r}{hint} (python -m march.inspect list shows "
            "every key; +key=value adds one, for a plug-in)"
        )
    text = str(err)
    if text.startswith("Ambiguous value for argument"):
        typed = text.split("'", 2)[1] if text.count("'") >= 2 else "an override"
        key = typed.split("=", 1)[0]
        return (
            f"{typed}: a comma makes a sweep, which needs -m (--multirun); for a list write "
            f"{key}=[...], for text with a comma quote it: {key}='...'"
        )
    if isinstance(cause, BaseException) and str(cause).strip():
        return f"{_one_line(err)}: {_one_line(cause)}"
    return _one_line(err)


def _sweep_jobs(args: Sequence[str], most: int = 16) -> list[list[str]]:
    """Command lines a multirun's sweeps (``seed=1,2``, ``range(...)``) expand to, enough to
    try every value once: the first job, then each other value of each sweep with the rest at
    their first (at most ``most``). A sweep that cannot be listed (``interval``, ``glob``) is
    left to the sweeper."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parser = OverridesParser.create()
    heads, values = [], []
    for arg in args:
        (ov,) = parser.parse_overrides([arg])
        if not ov.is_sweep_override():
            heads.append(arg)
            values.append([None])
            continue
        try:
            listed = list(ov.sweep_string_iterator())
        except Exception:  # noqa: BLE001 - interval / glob: the sweeper's to expand
            continue
        heads.append(arg.split("=", 1)[0])
        values.append(listed or [None])

    def line(choice: dict[int, str]) -> list[str]:
        return [
            h if vals == [None] else f"{h}={choice.get(i, vals[0])}"
            for i, (h, vals) in enumerate(zip(heads, values, strict=True))
        ]

    jobs = [line({})]
    for i, vals in enumerate(values):
        jobs += [line({i: v}) for v in vals[1:]]
    return jobs[:most]


def override_problem(argv: Sequence[str]) -> str | None:
    """One line saying why Hydra would refuse the command line ``argv`` (without the program
    name), else None: each override parsed on its own, then the config composed (Hydra's
    compose API: nothing written), each value of a multirun's sweeps once. Runs before
    ``@hydra.main`` (``march.train``), whose own report is many lines and exit 1; with
    ``HYDRA_FULL_ERROR=1``, or another Hydra flag on the line, Hydra reports itself."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    if full_error():
        return None
    flags = [a for a in argv if a.startswith("-")]
    if any(f not in HYDRA_FLAGS for f in flags):
        return None
    args = [a for a in argv if not a.startswith("-")]
    parser = OverridesParser.create()
    for arg in args:
        try:
            parser.parse_overrides([arg])
        except HydraException as err:
            return hydra_refusal(err, args)
    for job in _sweep_jobs(args) if flags else [args]:
        try:
            compose(job)
        except (HydraException, OmegaConfBaseException) as err:
            return hydra_refusal(err, job)
        except ConfigError:
            return None  # march's own checks: main says them, with the run's context
    return None
