"""Sweeps pin their scale: ``compute`` is never a sweep parameter.

Hydra resolves the sweep directory (named after the compute preset, conf/config.yaml) once, from
the sweep's own config, and each job's directory again from the job's. A sweep over ``compute``
would scatter its jobs and its ``multirun.yaml`` over several directories, and mix scales in one
comparison. :func:`sweep_problem` finds that before anything runs; the scale belongs in the sweep
file's ``defaults:`` (``- override /compute: gpu``) or on the command line (``compute=gpu``).

Pure data: no simulator import.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from omegaconf import OmegaConf

from march.config.registry import SWEEPS_DIR, searchpath_dirs

MULTIRUN_FLAGS = ("-m", "--multirun")
PINNED_GROUPS = ("compute",)


def _group(key: str) -> str:
    return key.lstrip("+~").split(".")[0].split("/")[0]


def _is_sweep_value(value: str) -> bool:
    v = value.strip()
    return "," in v or v.startswith(("choice(", "range(", "interval(", "glob("))


def sweep_problem(argv: Sequence[str], sweeps_dir: Path = SWEEPS_DIR) -> str | None:
    """One line saying why this ``march.train`` command line must not run, or None."""
    args = list(argv)
    if not any(a in MULTIRUN_FLAGS for a in args):
        return None
    for arg in args:
        if "=" not in arg or arg.startswith("-"):
            continue
        key, value = arg.split("=", 1)
        group = _group(key)
        if group in PINNED_GROUPS and _is_sweep_value(value):
            return (
                f"{arg}: {group} cannot be swept (the sweep's directories would be split by "
                f"scale); run one sweep per {group} preset, e.g. {group}={value.split(',')[0]}"
            )
        if group == "sweep":
            # Hydra's order: a searchpath tree's sweep/ group before the repository's sweeps/
            # (registered in the ConfigStore, searched last); the first found is the one run
            found = [d / "sweep" / f"{value}.yaml" for d in searchpath_dirs(args)]
            found.append(sweeps_dir / f"{value}.yaml")
            path = next((f for f in found if f.is_file()), None)
            if path is None:
                continue  # Hydra names the missing option itself
            params = OmegaConf.select(OmegaConf.load(path), "hydra.sweeper.params") or {}
            for pkey in params:
                if _group(str(pkey)) in PINNED_GROUPS:
                    return (
                        f"{path}: hydra.sweeper.params.{pkey} sweeps the "
                        f"{_group(str(pkey))} preset, which splits the sweep's output "
                        "directories; pin it in the sweep file's defaults: (- override "
                        "/compute: <preset>) or on the command line (compute=<preset>)"
                    )
    return None
