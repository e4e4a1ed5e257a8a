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


def compose(overrides: Sequence[str] = ()) -> DictConfig:
    """Compose conf/ with overrides (compute=auto resolved), as march.train would."""
    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = hydra.compose(config_name="config", overrides=list(overrides))
    return resolve_compute(cfg, overrides)


def load(overrides: Sequence[str] = ()) -> MarchConfig:
    """The checked config; ``extra_modules`` are imported first (their student parts and terms
    register before the config's checks read the registries)."""
    cfg = compose(overrides)
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
) -> object:
    """Parse ``[job] key=value ...``, compose the config and run the job with clear errors.
    ``check_reward``: check the reward terms too (imports the env's term modules; a job that
    builds no env may skip it)."""
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
        cfg = load(args)
        if check_reward:
            check_terms(cfg)  # every term known, its params valid: before any env
    except (HydraException, OmegaConfBaseException, ConfigError) as err:
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
    # Hydra's "Could not find 'reward/bogus'" is followed by the available options: keep them.
    if "Available options" in text:
        head = lines[0]
        opts = [ln for ln in lines[1:] if not ln.startswith("Available")]
        return f"{head}; available options: {', '.join(opts)}"
    return lines[0] if len(lines) == 1 else f"{lines[0]} ({lines[-1]})"
