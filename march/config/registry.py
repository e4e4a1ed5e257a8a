"""The registries of reward arms and student variants: read from the config groups themselves.

A reward arm is a ``conf/reward/<name>.yaml``, a student variant a ``conf/student/<name>.yaml``;
nothing else lists them. Each option names itself (``name:`` / ``variant:``, the file stem when
absent) and may carry display metadata that the config schema keeps and every run's
``config.yaml`` records, so the figures can draw a run without importing march:

* ``label``: how figures and tables name it (default: the name);
* ``color``: a matplotlib colour (default: one no other registered option uses);
* ``order``: position in legends and tables (lower first; ties by name).

Config checks, policies, analysis and tests read these lists, so a new option is its YAML alone
(plus, if it brings new code, only the function or module that implements it).

Pure data: no simulator import.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from functools import cache
from pathlib import Path

from omegaconf import OmegaConf

CONF_DIR = Path(__file__).resolve().parents[2] / "conf"
"""The repository's config tree (``conf/``)."""
SWEEPS_DIR = Path(__file__).resolve().parents[2] / "sweeps"
"""The paper's experiments (``sweeps/``), each the option ``+sweep=<name>``."""

NAME_KEY = {"reward": "name", "student": "variant"}
"""The key inside each group's YAML that names the option."""

DEFAULT_ORDER = 100
"""``order`` of an option that states none: after the paper's options."""


@dataclass(frozen=True)
class Option:
    """One registered option of a config group."""

    group: str
    name: str
    label: str
    color: str
    order: int
    path: Path
    data: dict
    """The option's YAML as plain data (e.g. a student variant's ``image``/``fusion``/``head``)."""


def _read(path: Path) -> dict:
    node = OmegaConf.to_container(OmegaConf.load(path), resolve=False)
    return node if isinstance(node, dict) else {}


@cache
def _options(group: str, conf_dirs: tuple[Path, ...]) -> tuple[Option, ...]:
    found: dict[str, Option] = {}
    for conf in conf_dirs:
        for path in sorted((conf / group).glob("*.yaml")):
            data = _read(path)
            name = str(data.get(NAME_KEY.get(group, "name")) or path.stem)
            found[name] = Option(
                group=group,
                name=name,
                label=str(data.get("label") or name),
                color=str(data.get("color") or ""),
                order=int(data.get("order", DEFAULT_ORDER)),
                path=path,
                data=data,
            )
    ordered = sorted(found.values(), key=lambda o: (o.order, o.name))
    return tuple(ordered)


def options(group: str, conf_dirs: Iterable[Path] = (CONF_DIR,)) -> tuple[Option, ...]:
    """The options of ``group`` (``reward`` or ``student``) in display order; a later conf dir
    overrides an earlier one's option of the same name."""
    return _options(group, tuple(Path(d) for d in conf_dirs))


def names(group: str, conf_dirs: Iterable[Path] = (CONF_DIR,)) -> tuple[str, ...]:
    """The option names of ``group`` in display order."""
    return tuple(o.name for o in options(group, conf_dirs))


def searchpath_dirs(argv: Sequence[str]) -> list[Path]:
    """The ``file://`` directories of a ``hydra.searchpath=[...]`` override, in order."""
    out: list[Path] = []
    for arg in argv:
        if arg.lstrip("+").startswith("hydra.searchpath="):
            items = arg.split("=", 1)[1].strip("[]")
            out += [Path(i.strip()[len("file://") :]) for i in items.split(",") if "file://" in i]
    return out
