"""A run directory is owned and guarded (``march.train``; docs/reliability.md).

- :func:`before_hydra`: on the command line as typed, before Hydra creates or writes anything:
  a key set twice is refused; the output directory (``hydra.run.dir`` / ``hydra.sweep.dir``,
  or the literal part of the configured template) must be creatable and writable; a directory
  that already holds a run is checked for links and locked now (:mod:`march.store.run_lock`),
  and Hydra is told not to rewrite the run's ``.hydra/``.
- :func:`claim`: in ``main``, the lock for the run's whole life (taken here if
  :func:`before_hydra` could not: a new directory, a sweep job) and no link among its files.
- :func:`check_run_checkpoints`: the run's newest teacher and student checkpoints read and
  validated (config, iteration, env steps) before any env is built, and kept for the resume
  that uses them (:func:`march.store.checkpoint.keep_checked`: the bytes checked are the bytes
  used); :func:`check_run_tables`: its CSV tables row by row (:mod:`march.store.run_tables`).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from pathlib import Path

from omegaconf import OmegaConf

from march.config import ConfigError, MarchConfig
from march.config.cli import check_output_dir, duplicate_overrides, literal_prefix
from march.config.registry import CONF_DIR
from march.store import run_lock

RUN_FILES = (
    "config.yaml",
    "metrics.csv",
    "eval.csv",
    "status.json",
    "summary.json",
    "teacher",
    "student",
)
"""What a march run writes into its directory (besides Hydra's ``train.log`` and ``.hydra/``)."""
CHECKED_FOR_LINKS = ("", "teacher", "student", ".hydra")
"""The run directory itself and the folders march writes in: none of their entries may be a
symbolic link (wandb's own folder keeps its ``latest-run`` link)."""


def holds_run(run_dir: Path) -> bool:
    """Whether ``run_dir`` holds (part of) a march run."""
    return any(os.path.lexists(Path(run_dir) / name) for name in RUN_FILES)


def refuse_links(run_dir: Path, option: str) -> None:
    """One line if a file march writes in ``run_dir`` is a symbolic link (it would write
    through it, somewhere else)."""
    for sub in CHECKED_FOR_LINKS:
        folder = Path(run_dir) / sub
        if sub and os.path.islink(folder):
            found = [folder]
        elif folder.is_dir():
            found = sorted(p for p in folder.iterdir() if p.is_symlink())
        else:
            continue
        if found:
            raise ConfigError(
                f"{option}={run_dir}: {found[0]} is a symbolic link (to {os.readlink(found[0])}); "
                "march writes no run file through a link: replace it with the file itself"
            )


def claim(run_dir: Path, option: str) -> list[str]:
    """Lock ``run_dir`` for this process's life and refuse links in it; note lines."""
    refuse_links(run_dir, option)
    lock = run_lock.acquire(run_dir, option)
    return [n] if (n := run_lock.stale_note(lock)) else []


def _value(args: Sequence[str], key: str) -> str | None:
    found = [a.split("=", 1)[1] for a in args if a.lstrip("+").startswith(key + "=")]
    return found[-1] if found else None


def before_hydra(argv: list[str], multirun: bool, rank0: bool = True) -> list[str]:
    """Checks on the command line before Hydra starts; returns argv (with
    ``hydra.output_subdir=null`` added for a directory that already holds a run). Raises
    :class:`ConfigError` with one line. ``march.train`` runs :func:`check_files_before_hydra`
    first (the same files, judged without torch); every refusal of those is made here too,
    once the command line is composed."""
    args = argv[1:]
    if twice := duplicate_overrides(args):
        raise ConfigError(twice)
    key = "hydra.sweep.dir" if multirun else "hydra.run.dir"
    explicit = _value(args, key)
    if explicit is None:
        template = OmegaConf.load(CONF_DIR / "config.yaml").hydra.run
        if multirun:
            template = OmegaConf.load(CONF_DIR / "config.yaml").hydra.sweep
        template = OmegaConf.to_container(template, resolve=False)["dir"]
        check_output_dir(literal_prefix(str(template)), key)
        return argv
    run_dir = Path(explicit)
    if multirun or "${" in explicit or not rank0 or not holds_run(run_dir):
        check_output_dir(literal_prefix(explicit), key)
        return argv
    # An existing run: checked and locked before Hydra writes its job log there (the lock first:
    # a second writer leaves not even a write probe in it); Hydra's record of the run's first
    # launch (.hydra/) is left as it was.
    resumed = _value(args, "resume")
    claim(run_dir, "resume" if resumed else key)
    check_output_dir(run_dir, key)
    _check_before_hydra(run_dir, args, "resume" if resumed else key)
    if _value(args, "hydra.output_subdir") is None:
        argv = [*argv, "hydra.output_subdir=null"]
    return argv


def check_files_before_hydra(argv: list[str], multirun: bool, rank0: bool = True) -> None:
    """The files the command line hands in, judged without torch before any config is composed
    (composing compute=auto, or Hydra naming the run directory after the preset, asks torch for
    CUDA: ~250 MB resident for the import alone), so that a crafted file is one line in about
    50 MB (issue 59: under 200 MB): the checkpoints it names (``teacher_ckpt=``,
    ``student_ckpt=``, a literal path: their zip directories) and, for the run directory it
    points at (``hydra.run.dir=``, which ``resume=`` sets), config.yaml's YAML, its tables row
    by row and its newest checkpoints' zip directories. :class:`ConfigError`, one line. What
    needs a composed config (the override rules, the checkpoints' contents) follows in
    :func:`before_hydra` and ``main``; a missing file, or a value Hydra has yet to read, is left
    to them."""
    from march.store.bounded_read import FileRefused
    from march.store.checkpoint_file import CheckpointError, check_file
    from march.store.resume_rules import saved_config_text

    args = argv[1:]
    key = "hydra.sweep.dir" if multirun else "hydra.run.dir"
    explicit = _value(args, key)
    try:
        for name in ("teacher_ckpt", "student_ckpt"):
            path = _value(args, name)
            if path and "${" not in path and os.path.lexists(path):
                check_file(path, f"{name}={path}")
        if explicit is None or multirun or "${" in explicit or not rank0:
            return
        run_dir = Path(explicit)
        if not holds_run(run_dir) or not (run_dir / "config.yaml").is_file():
            return  # no run there, or run files without a config: main says so
        option = "resume" if _value(args, "resume") else key
        saved_config_text(run_dir, option)
        check_run_tables(run_dir, option)
        newest_checkpoints(run_dir, option)
    except (FileRefused, CheckpointError) as err:
        raise ConfigError(str(err)) from None


def _check_before_hydra(run_dir: Path, args: Sequence[str], option: str) -> None:
    """A run pointed at (``resume=`` or a new run in its directory): its files read through the
    gate now, before Hydra appends to the run's ``train.log`` and before any env, so that a bad
    file (a YAML bomb in config.yaml, a non-numeric metrics row, a zip-bomb checkpoint) or a
    refused override is one line and leaves the directory as it was. Its config.yaml
    (:func:`march.store.resume_rules.resume_config` / :func:`~march.store.resume_rules.
    adopt_config`), then its tables and newest checkpoints (:func:`check_run_checkpoints`). ``main`` checks again with the final
    config (a policy checkpoint applied), the process group's size known."""
    from march.config.cli import load
    from march.store.bounded_read import FileRefused
    from march.store.checkpoint_file import CheckpointError
    from march.store.resume_rules import adopt_config, resume_config

    if not (run_dir / "config.yaml").is_file():
        return  # main refuses it in one line (run files without a config)
    # march.train judged these files without torch already (check_files_before_hydra); now
    # they are read against the config composed from the command line.
    task = [a for a in args if "=" in a and not a.lstrip("+~").startswith("hydra")]
    try:
        cfg = load(task)
    except Exception:  # noqa: BLE001 - a bad override: Hydra and main report it in one line
        return
    try:
        if option == "resume":
            cfg, _ = resume_config(run_dir, cfg, task)
        elif cfg.teacher_ckpt or cfg.student_ckpt:
            return  # a checkpoint may change the policy: main compares
        else:
            adopt_config(run_dir, cfg)
        check_run_checkpoints(run_dir, cfg, option)  # its tables first
    except (FileRefused, CheckpointError) as err:
        raise ConfigError(str(err)) from None


def check_run_checkpoints(
    run_dir: Path,
    cfg: MarchConfig,
    option: str,
    world_mismatch: Callable[[dict], str | None] | None = None,
) -> list[str]:
    """The run's CSV tables checked row by row (:func:`check_run_tables`); then its newest
    checkpoints read (CPU) through the gate (:func:`march.store.gate.
    read_checkpoint`: the command line's checks, weights against config) and check that they
    belong to this run (no difference a resume could not make); before any env is built.
    ``world_mismatch``: why this process group cannot resume a payload (``march.learn.
    distributed.world_mismatch``; the training room sits above this one)."""
    check_run_tables(run_dir, option)  # before anything in the directory changes
    found = newest_checkpoints(run_dir, option)  # every file's zip directory first
    # torch (~250 MB resident) only now: a refused table or file was told without it.
    from march.store.checkpoint import keep_checked
    from march.store.gate import read_checkpoint
    from march.store.resume_rules import config_differences

    notes = []
    for kind, path in found.items():
        label = f"{option}={run_dir}: {path}"
        payload, saved = read_checkpoint(
            str(path), kind, cfg.extra_modules, source=label, world_mismatch=world_mismatch
        )
        if saved is not None:
            # Rank 0 writes checkpoints with the run's own seed (march.learn.distributed).
            unsafe, _ = config_differences(saved, cfg)
            if unsafe:
                raise ConfigError(
                    f"{label}: written by another config than the run's config.yaml "
                    f"({'; '.join(unsafe[:4])}); it does not belong to this run"
                )
        keep_checked(path, payload)  # the resume uses these bytes, not a second read
        notes.append(f"[{kind}] checked {path}: iteration {payload['iteration']}")
    return notes


def newest_checkpoints(run_dir: Path, option: str) -> dict[str, Path]:
    """The run's newest teacher and student checkpoints, by kind, each judged without torch
    (:func:`march.store.checkpoint_file.check_file`: no link, bounded, its zip directory);
    :class:`~march.store.checkpoint_file.CheckpointError` at the first refused one."""
    from march.store.checkpoint_file import check_file, latest_checkpoint

    found = {}
    for kind in ("teacher", "student"):
        folder = Path(run_dir) / kind
        path = latest_checkpoint(folder) if folder.is_dir() else None
        if path is not None:
            check_file(path, f"{option}={run_dir}: {path}")
            found[kind] = path
    return found


def check_run_tables(run_dir: Path, option: str) -> None:
    """Every CSV table of the run checked row by row (:func:`march.store.run_tables.
    check_run_tables`) before anything in the directory changes; one :class:`ConfigError`."""
    from march.store.bounded_read import FileRefused
    from march.store.run_tables import check_run_tables as check_tables

    try:
        check_tables(run_dir, option)
    except FileRefused as err:
        raise ConfigError(str(err)) from None


_HYDRA_JOB_FILES = {"train.log", ".hydra/config.yaml", ".hydra/hydra.yaml", ".hydra/overrides.yaml"}
"""What Hydra writes into a run directory before march reads the config."""


def drop_refused(path: Path) -> None:
    """A run refused before it started leaves no directory behind. Hydra made the directory,
    its job log and ``.hydra/`` before march read the config; they are removed only while they
    are all the directory holds."""
    try:
        found = {p.relative_to(path).as_posix(): p for p in path.rglob("*") if p.is_file()}
    except OSError:
        return
    if "train.log" not in found or not set(found) <= _HYDRA_JOB_FILES:
        return
    try:  # every rank of a refused torchrun job may be removing the same files
        for file in found.values():
            file.unlink(missing_ok=True)
        for folder in (path / ".hydra", path):
            if folder.is_dir() and not any(folder.iterdir()):
                folder.rmdir()
    except OSError:
        pass
