"""The registry of student parts: ``image``, ``fusion`` and ``head`` values, each mapped to its
builder and its own config block.

A part is registered with :func:`register_part` (``march.policies.student_part`` is its
decorator): a kind, a name, optionally a config dataclass (its *block*, set under
``student.parts.<name>`` in YAML or on the command line) and the builder
(``march.policies.part_builders``). The paper's parts keep their hyper-parameters where older
configs and checkpoints have them (``student.d_model``, ``student.fusion_mlp``, ...): their
names are declared here so the default config needs no import; a new part (``gru``) brings its
own block. An unknown value is one line naming the known ones, after the modules that define
parts were imported (march's own, :data:`BUILTIN_PART_MODULES`, by name, like a plug-in; a
user's come from ``extra_modules``).

Pure data: no simulator import.
"""

from __future__ import annotations

import dataclasses
import importlib
from dataclasses import dataclass
from typing import Any

from march.errors import ConfigError

KINDS = ("image", "fusion", "head")
BUILTIN_PART_MODULES = ("march.policies.part_builders",)
"""march's own part builders, imported by name the first time a value is not yet known."""


@dataclass
class PartSpec:
    kind: str
    name: str
    block: type | None = None
    """The part's config dataclass (``student.parts.<name>``), or None (no block of its own)."""
    builder: Any = None
    """The object that builds and runs the part (march.policies.part_builders)."""
    doc: str = ""


PARTS: dict[str, dict[str, PartSpec]] = {k: {} for k in KINDS}
"""kind -> name -> spec."""

_LEGACY = {
    "image": {"cnn": "the depth CNN (student.cnn_*)", "none": "the image is not read"},
    "fusion": {
        "transformer": "tokens + attention (student.d_model, n_heads, n_layers, ...)",
        "mlp": "an MLP over the concatenation (student.fusion_mlp)",
    },
    "head": {
        "mdn": "mixture density network, NLL of teacher samples (student.num_modes, ...)",
        "deterministic": "one action, Huber against the teacher mean (student.huber_delta)",
    },
}
for _kind, _names in _LEGACY.items():
    for _name, _doc in _names.items():
        PARTS[_kind][_name] = PartSpec(_kind, _name, doc=_doc)


def register_part(
    kind: str, name: str, builder: Any = None, block: type | None = None, doc: str = ""
) -> PartSpec:
    """Register (or give its builder to) the part ``name`` of ``kind``."""
    if kind not in KINDS:
        raise ConfigError(f"student part kind {kind!r}; choose one of {', '.join(KINDS)}")
    if block is not None and not dataclasses.is_dataclass(block):
        raise ConfigError(f"student part {kind}={name}: its block must be a dataclass")
    spec = PARTS[kind].get(name)
    if spec is None:
        spec = PARTS[kind][name] = PartSpec(kind, name, block, builder, doc)
    else:
        old = spec.builder
        if old is not None and builder is not None and _origin(old) != _origin(builder):
            raise ConfigError(f"student part {kind}={name} exists already; choose another name")
        spec.builder = builder if builder is not None else spec.builder
        spec.block = block if block is not None else spec.block
        spec.doc = doc or spec.doc
    return spec


def _origin(obj: Any) -> str:
    return f"{getattr(obj, '__module__', '?')}.{getattr(obj, '__qualname__', '?')}"


def load_builtin_parts() -> None:
    for module in BUILTIN_PART_MODULES:
        importlib.import_module(module)


def known(kind: str) -> tuple[str, ...]:
    return tuple(PARTS[kind])


def check_value(kind: str, value: str) -> None:
    """``student.<kind>=<value>`` is a registered part, else one line naming the known ones."""
    if value not in PARTS[kind]:
        load_builtin_parts()
    if value not in PARTS[kind]:
        raise ConfigError(
            f"student.{kind}={value!r} is not a registered {kind} part; choose one of "
            f"{', '.join(known(kind))} (a part of your own: its module in extra_modules=[...])"
        )


def block(parts: dict[str, Any], kind: str, name: str) -> Any:
    """The config block of part ``name``: its dataclass from ``student.parts.<name>`` (defaults
    for keys not given; an unknown key or a bad value is one line), or None."""
    spec = PARTS[kind][name]
    given = dict(parts.get(name) or {})
    if spec.block is None:
        if given:
            raise ConfigError(
                f"student.parts.{name}: the {kind} part {name} has no block of its own; its "
                "settings are student.* keys"
            )
        return None
    fields = {f.name for f in dataclasses.fields(spec.block)}
    unknown = sorted(set(given) - fields)
    if unknown:
        raise ConfigError(
            f"student.parts.{name}: unknown key(s) {unknown}; its keys: {', '.join(sorted(fields))}"
        )
    try:
        return spec.block(**given)
    except (TypeError, ValueError) as err:
        raise ConfigError(f"student.parts.{name}: {err}") from None


def check_parts(parts: dict[str, Any], chosen: dict[str, str]) -> None:
    """Every ``student.parts.<name>`` names a registered part; the chosen parts' blocks valid."""
    everything = {n: k for k in KINDS for n in PARTS[k]}
    for name in parts:
        if name not in everything:
            load_builtin_parts()
            everything = {n: k for k in KINDS for n in PARTS[k]}
        if name not in everything:
            raise ConfigError(
                f"student.parts.{name}: no part is called {name!r}; parts with a block: "
                + ", ".join(n for k in KINDS for n, s in PARTS[k].items() if s.block)
            )
    for kind, name in chosen.items():
        block(parts, kind, name)
