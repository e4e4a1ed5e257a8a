"""A config read from a file is data: nothing in it is resolved, and nothing it names is imported.

A run's ``config.yaml`` and a checkpoint's saved config come from the disk, where anyone may
have edited them. Two rules hold for both, one copy each, used by the checkpoint gate
(:mod:`march.store.gate`), the policy a checkpoint defines (:mod:`march.store.provenance`) and
the resume rules (:mod:`march.store.resume_rules`):

- :func:`interpolations`: no ``${...}`` interpolation or resolver call anywhere (march never
  writes one; resolving it would run ``oc.env``, ``oc.decode`` or a plug-in's resolver on the
  file's say);
- :func:`check_named_modules`: a module the file names (``extra_modules``) is imported only
  when the user names it too.

Pure data: no torch, no simulator.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from march.config import ConfigError


def interpolations(node: Any, where: str = "") -> list[str]:
    """Keys (dotted) of ``node`` (plain dicts and lists, as parsed, unresolved) whose key or
    string value holds ``${``."""
    found = []
    items = (
        node.items()
        if isinstance(node, dict)
        else enumerate(node)
        if isinstance(node, list | tuple)
        else ()
    )
    for k, v in items:
        key = (
            f"{where}.{k}" if where and isinstance(k, str) else f"{where}[{k}]" if where else str(k)
        )
        if isinstance(k, str) and "${" in k:
            found.append(key)
        elif isinstance(v, str):
            if "${" in v:
                found.append(key)
        else:
            found += interpolations(v, key)
    return found


def check_named_modules(saved: Any, named: Sequence[str], label: str) -> None:
    """The modules a file's config names (``extra_modules``) must all be named by the user too:
    a file never makes march import a module. One line naming the first other module."""
    if saved in (None, [], ()):
        return
    if not isinstance(saved, list | tuple) or not all(isinstance(m, str) for m in saved):
        raise ConfigError(f"{label}: its extra_modules {saved!r} is not a list of module names")
    for name in saved:
        if name not in named:
            raise ConfigError(
                f"{label}: its config names module {name!r} (extra_modules), which you did not "
                "name; march imports a module a file names only when you name it too: add "
                f"extra_modules=[{name}] to the command line (or your config) if you trust it"
            )
