"""The reward-term registry and the plug-in modules: one registration path for every term.

A term is a function ``f(env, **params) -> (num_envs,) tensor`` registered under a name with
its default parameters and what it needs from the env (:data:`NEEDS`). march's own terms
(``march.env.rewards``) and a user's (any module, named in ``extra_modules``) register the
same way, with :func:`register_term` (``march.env.rewards.reward_term`` is its decorator).

``reward.terms.<name>`` is a weight or ``{weight: w, params: {...}}``; :func:`check_reward`
checks the names, the params against the function's signature and the needs, in one line,
before any env is built. The modules that define terms are imported by name
(:func:`import_term_modules`): march's own first (:data:`BUILTIN_TERM_MODULES`), then
``extra_modules``. That is the only way this room reaches the env: by a module name, as a
plug-in, never by a static import.

Checking a config needs only each term's name, parameter names and needs, not its function:
:func:`check_terms` knows march's own terms from :data:`march.config.term_table.BUILTIN_TERMS`
(generated from this registry, compared with it by a test) and imports only ``extra_modules``,
so a tool that refuses its config does so without importing the simulator (~5 s a process).
The env imports march's term modules for real; their registrations replace the table's entries.

Pure data: no simulator import.
"""

from __future__ import annotations

import importlib
import inspect
import math
import sys
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from march.errors import ConfigError

BUILTIN_TERM_MODULES = ("march.env.rewards",)
"""march's own term modules, imported like a plug-in before ``extra_modules``."""

NEEDS = {
    "reference": "the planner + HLIP reference command term (`reference`): the env builds it, "
    "its privileged observation and the planner_infeasible termination",
    "height_scan": "the terrain height scan around the pelvis "
    "(march.env.observations.terrain_height_scan, computed from the course boxes: every env "
    "has it)",
}
"""What a term may declare it needs, and what the env provides for it."""


FUNCTION_DEFAULT = "(the function's default)"
"""A table entry's value for a parameter the function gives a default (the value itself lives
in the function, known once its module is imported)."""


@dataclass(frozen=True)
class TermSpec:
    """One registered reward term (``func`` None: an entry of march's term table, its function
    not imported yet; ``table`` then holds what its signature says)."""

    name: str
    func: Callable[..., Any] | None
    params: dict[str, Any] = field(default_factory=dict)
    """Default keyword arguments (a YAML's ``params`` overrides them key by key)."""
    needs: frozenset[str] = frozenset()
    """What the term reads beyond mjlab's robot and scene (keys of :data:`NEEDS`)."""
    doc: str = ""
    table: Mapping[str, Any] | None = None
    """A table entry (:func:`table_entry`) standing for the function until it is imported."""

    @property
    def origin(self) -> str:
        if self.table is not None:
            return self.table["origin"]
        return f"{getattr(self.func, '__module__', '?')}.{getattr(self.func, '__qualname__', '?')}"

    def parameters(self) -> dict[str, Any]:
        """Every keyword the function takes (besides the env) -> its value: the registered
        default, the function's own default (:data:`FUNCTION_DEFAULT` in a table entry), or
        ``inspect.Parameter.empty`` (required)."""
        if self.table is not None:
            required = set(self.table["required"])
            return {
                p: self.params.get(
                    p, inspect.Parameter.empty if p in required else FUNCTION_DEFAULT
                )
                for p in self.table["parameters"]
            }
        out: dict[str, Any] = {}
        for i, p in enumerate(inspect.signature(self.func).parameters.values()):
            if i == 0 or p.kind in (p.VAR_POSITIONAL, p.VAR_KEYWORD):
                continue
            out[p.name] = self.params.get(p.name, p.default)
        return out

    def takes_any(self) -> bool:
        """The function takes ``**kwargs`` (any params)."""
        return self.table["takes_any"] if self.table is not None else _takes_any(self.func)


def table_entry(spec: TermSpec) -> dict[str, Any]:
    """What checking a config needs of a term, as plain data (march.config.term_table)."""
    params = spec.parameters()
    return {
        "origin": spec.origin,
        "parameters": list(params),
        "required": [k for k, v in params.items() if v is inspect.Parameter.empty],
        "registered": sorted(spec.params),
        "needs": sorted(spec.needs),
        "takes_any": spec.takes_any(),
        "doc": spec.doc,
    }


def from_table(name: str, entry: Mapping[str, Any]) -> TermSpec:
    """A table entry as a spec: its registered params by name only (their values are the
    function's module's, :data:`FUNCTION_DEFAULT` until it is imported)."""
    params = dict.fromkeys(entry["registered"], FUNCTION_DEFAULT)
    return TermSpec(name, None, params, frozenset(entry["needs"]), entry["doc"], entry)


TERMS: dict[str, TermSpec] = {}
"""Every registered term, by name."""


def register_term(
    name: str,
    func: Callable[..., Any],
    params: Mapping[str, Any] | None = None,
    needs: Iterable[str] = (),
) -> TermSpec:
    """Register ``func`` as the reward term ``name``. A name taken by another function is an
    error (a term means one thing in every arm); the same function again (a module imported
    twice) replaces itself, as march's own function replaces its table entry."""
    needs = frozenset(needs)
    unknown = sorted(needs - set(NEEDS))
    if unknown:
        raise ConfigError(
            f"reward term {name!r}: unknown need(s) {unknown}; known: {', '.join(NEEDS)}"
        )
    spec = TermSpec(
        name, func, dict(params or {}), needs, (inspect.getdoc(func) or "").split("\n")[0]
    )
    old = TERMS.get(name)
    if old is not None and old.origin != spec.origin:
        raise ConfigError(
            f"reward term {name!r} exists already ({old.origin}); choose another name"
        )
    bad = sorted(set(spec.params) - set(spec.parameters())) if not spec.takes_any() else []
    if bad:
        raise ConfigError(f"reward term {name!r}: {bad} are not parameters of {spec.origin}")
    TERMS[name] = spec
    return spec


def _takes_any(func: Callable[..., Any]) -> bool:
    kinds = [p.kind for p in inspect.signature(func).parameters.values()]
    return inspect.Parameter.VAR_KEYWORD in kinds


def import_extra_modules(extra_modules: Iterable[str]) -> None:
    """Import the user's plug-in modules (dotted names on ``sys.path``), once each; a module
    that cannot be imported is one line."""
    for name in extra_modules:
        if not isinstance(name, str) or not all(p.isidentifier() for p in name.split(".")):
            raise ConfigError(f"extra_modules: {name!r} is not a dotted module name")
        try:
            importlib.import_module(name)
        except ImportError as err:
            raise ConfigError(
                f"extra_modules: cannot import {name!r} ({err}); put its directory on "
                "PYTHONPATH (or hydra.searchpath for YAML only) or install it"
            ) from None


def import_term_modules(extra_modules: Iterable[str] = ()) -> None:
    """Import march's term modules, then ``extra_modules``: every term registered."""
    for name in BUILTIN_TERM_MODULES:
        importlib.import_module(name)
    import_extra_modules(extra_modules)


def known_terms(extra_modules: Iterable[str] = ()) -> None:
    """Every term known for checking a config: march's own from the term table where their
    modules are not imported (nothing of the simulator imported), then ``extra_modules``
    imported (their registrations are real)."""
    if not all(m in sys.modules for m in BUILTIN_TERM_MODULES):
        from march.config.term_table import BUILTIN_TERMS

        for name, entry in BUILTIN_TERMS.items():
            TERMS.setdefault(name, from_table(name, entry))
    import_extra_modules(extra_modules)


def check_terms(cfg: Any) -> None:
    """The run's terms known (march's and ``cfg.extra_modules``) and ``cfg.reward`` valid
    against them: one line, before any env is built, without importing the simulator."""
    known_terms(cfg.extra_modules)
    check_reward(cfg.reward)


def term_weight(value: Any) -> float:
    """The weight of a ``reward.terms`` entry (a number or ``{weight, params}``)."""
    return float(value["weight"]) if isinstance(value, Mapping) else float(value)


def term_params(value: Any) -> dict[str, Any]:
    """The params a ``reward.terms`` entry sets (``{}`` for a bare weight)."""
    return dict(value.get("params") or {}) if isinstance(value, Mapping) else {}


def check_entry(name: str, value: Any) -> None:
    """The shape of one ``reward.terms`` entry, without the registry (the config's own check)."""
    where = f"reward.terms.{name}"
    if isinstance(value, Mapping):
        extra = sorted(set(value) - {"weight", "params"})
        if extra or "weight" not in value:
            raise ConfigError(
                f"{where}={dict(value)}: use a weight or {{weight: w, params: {{...}}}}"
                + (f" (unknown keys {extra})" if extra else " (no weight)")
            )
        if not isinstance(value.get("params") or {}, Mapping):
            raise ConfigError(
                f"{where}.params={value['params']!r} must be a mapping of name: value"
            )
        weight = value["weight"]
    else:
        weight = value
    if isinstance(weight, bool) or not isinstance(weight, (int, float)):
        raise ConfigError(f"{where}={weight!r} must be a number (the term's weight)")
    if not math.isfinite(weight):
        raise ConfigError(f"{where}={weight} must be finite")


def resolve(name: str, value: Any) -> tuple[TermSpec, float, dict[str, Any]]:
    """(spec, weight, params) of one ``reward.terms`` entry: the params checked against the
    function's signature and every required parameter given, in one line."""
    spec = TERMS[name]
    given = term_params(value)
    known = spec.parameters()
    if not spec.takes_any():
        unknown = sorted(set(given) - set(known))
        if unknown:
            listed = ", ".join(known) or "none"
            raise ConfigError(
                f"reward.terms.{name}.params: {unknown} not parameter(s) of {spec.origin}; "
                f"its parameters: {listed}"
            )
    params = {**spec.params, **given}
    missing = [k for k, v in known.items() if v is inspect.Parameter.empty and k not in params]
    if missing:
        raise ConfigError(
            f"reward.terms.{name}: {spec.origin} needs {missing}; set them in "
            f"reward.terms.{name}.params"
        )
    return spec, term_weight(value), params


def check_reward(reward: Any, label: str = "") -> None:
    """Every term of ``reward.terms`` registered, its params valid (one line otherwise)."""
    arm = label or getattr(reward, "name", "?")
    if not reward.terms:
        raise ConfigError(f"reward={arm} has no terms; add reward.terms in conf/reward/")
    unknown = sorted(set(reward.terms) - set(TERMS))
    if unknown:
        raise ConfigError(
            f"reward={arm}: unknown reward term(s) {unknown}; known: {', '.join(sorted(TERMS))}"
            " (a term of your own: its module in extra_modules=[...])"
        )
    for name, value in reward.terms.items():
        resolve(name, value)


def needs(reward: Any) -> frozenset[str]:
    """What the terms of ``reward`` need (a weight of 0 included: mjlab still builds the
    term), plus the observation's (``reward.observe_reference``: an observation that needs the
    reference)."""
    out: set[str] = set()
    for name in reward.terms:
        if name in TERMS:
            out |= TERMS[name].needs
    if getattr(reward, "observe_reference", False):
        out.add("reference")
    return frozenset(out)
