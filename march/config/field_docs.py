"""The configuration reference, read from the config dataclasses themselves (``docs/``).

Every field of :class:`march.config.MarchConfig` and its sections: its type, default, unit (the
first ``[...]`` of its docstring), the values its section's ``__post_init__`` allows (read from
the calls to the :mod:`march.config.checks` helpers: ``check_one_of``, ``check_interval``,
``check_at_least``, ``check_positive``, ``check_identifier``) and its docstring; then every option of every ``conf/`` group with
its YAML. The mkdocs hook (``docs/hooks/march_docs.py``) writes it as a page at build time, so it
cannot go stale; ``tests/test_docs.py`` fails when a field has no docstring. Pure data: no
simulator import.
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import re
import sys
import textwrap
from dataclasses import MISSING, dataclass
from pathlib import Path
from typing import Any

from march.config import checks

CONF = Path(__file__).resolve().parents[2] / "conf"
"""The Hydra config groups (``conf/<group>/<option>.yaml``)."""
_UNIT = re.compile(r"\[([A-Za-z%][A-Za-z/%^0-9 *-]{0,11})\]")
"""A unit in brackets: ``[m]``, ``[rad/s]``, ``[N m]`` (not ``[0, 1]`` nor ``[my_lab.terms]``)."""


@dataclass
class FieldDoc:
    """One documented field."""

    path: str
    """Dotted key as on the command line (``env.sim_dt``)."""
    type: str
    default: str
    unit: str
    allowed: str
    doc: str


def attribute_docs(cls: type) -> dict[str, str]:
    """{field: docstring} from the string literal under each annotated attribute of ``cls``."""
    try:
        source = textwrap.dedent(inspect.getsource(cls))
    except (OSError, TypeError):
        return {}
    body = ast.parse(source).body[0].body  # type: ignore[attr-defined]
    out: dict[str, str] = {}
    for stmt, nxt in zip(body, body[1:] + [None], strict=True):
        if (
            isinstance(stmt, ast.AnnAssign)
            and isinstance(stmt.target, ast.Name)
            and isinstance(nxt, ast.Expr)
            and isinstance(nxt.value, ast.Constant)
            and isinstance(nxt.value.value, str)
        ):
            out[stmt.target.id] = inspect.cleandoc(nxt.value.value)
    return out


def _constant(node: ast.AST, module: Any) -> Any:
    """The value of a literal or a module-level name (checks' tuples), else None."""
    try:
        return ast.literal_eval(node)
    except ValueError:
        pass
    if isinstance(node, ast.Name):
        return getattr(module, node.id, getattr(checks, node.id, None))
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub):
        inner = _constant(node.operand, module)
        return -inner if isinstance(inner, (int, float)) else None
    return None


def allowed_values(cls: type) -> dict[str, str]:
    """{field: allowed values} from the check calls in ``cls.__post_init__``."""
    post = cls.__dict__.get("__post_init__")
    if post is None:
        return {}
    module = sys.modules[cls.__module__]
    tree = ast.parse(textwrap.dedent(inspect.getsource(post)))
    out: dict[str, str] = {}
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Name)):
            continue
        args, name = node.args, node.func.id
        if len(args) < 3 or not isinstance(args[1], ast.Constant):
            continue
        key = args[1].value
        kw = {k.arg: _constant(k.value, module) for k in node.keywords}
        if name == "check_one_of" and len(args) >= 4:
            valid = _constant(args[3], module)
            if valid:
                out[key] = "one of " + ", ".join(f"`{v}`" for v in valid)
        elif name == "check_positive":
            out[key] = "> 0"
        elif name == "check_identifier":
            out[key] = "a name: letters, digits, underscores"
        elif name == "check_at_least" and len(args) >= 4:
            lo = _constant(args[3], module)
            out[key] = f">= {lo}" if lo is not None else out.get(key, "")
        elif name == "check_interval" and len(args) >= 5:
            lo, hi = _constant(args[3], module), _constant(args[4], module)
            left = "(" if kw.get("lo_open") else "["
            right = ")" if kw.get("hi_open") else "]"
            lo_s = "?" if lo is None else lo
            hi_s = ast.unparse(args[4]).replace("self.", "") if hi is None else hi
            out[key] = f"{left}{lo_s}, {hi_s}{right}"
    return out


def _default(f: dataclasses.Field) -> Any:
    if f.default is not MISSING:
        return f.default
    if f.default_factory is not MISSING:  # type: ignore[misc]
        return f.default_factory()  # type: ignore[misc]
    return MISSING


def _show(value: Any) -> str:
    if value is MISSING:
        return "(required)"
    if isinstance(value, str):
        return f'"{value}"'
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _type_name(tp: Any) -> str:
    text = tp if isinstance(tp, str) else getattr(tp, "__name__", str(tp))
    return text.replace("typing.", "")


def walk(cls: type, prefix: str = "") -> list[FieldDoc]:
    """Every leaf field of ``cls`` (a config dataclass) and its nested sections, in order."""
    docs, allowed = attribute_docs(cls), allowed_values(cls)
    out: list[FieldDoc] = []
    for f in dataclasses.fields(cls):
        path = f"{prefix}{f.name}"
        default = _default(f)
        if dataclasses.is_dataclass(default) and not isinstance(default, type):
            out.extend(walk(type(default), path + "."))
            continue
        doc = docs.get(f.name, "")
        unit = _UNIT.search(doc)
        out.append(
            FieldDoc(
                path=path,
                type=_type_name(f.type),
                default=_show(default),
                unit=unit.group(1) if unit else "",
                allowed=allowed.get(f.name, ""),
                doc=doc,
            )
        )
    return out


def sections(cls: type, prefix: str = "") -> list[tuple[str, type]]:
    """(dotted name, class) of ``cls`` and every nested config section, depth first."""
    out = [(prefix.rstrip(".") or "(top level)", cls)]
    for f in dataclasses.fields(cls):
        default = _default(f)
        if dataclasses.is_dataclass(default) and not isinstance(default, type):
            out.extend(sections(type(default), f"{prefix}{f.name}."))
    return out


def undocumented(cls: type) -> list[str]:
    """Dotted keys of the fields without a docstring."""
    return [d.path for d in walk(cls) if not d.doc.strip()]


def _cell(text: str) -> str:
    text = " ".join(text.split()).replace("|", "\\|")
    return text.replace("<", "&lt;")


def render_markdown(cls: type, conf: Path = CONF) -> str:
    """The configuration reference page (Markdown)."""
    lines = [
        "# Configuration reference",
        "",
        "Generated when the site is built, from the config dataclasses (`march/config/`) and",
        "their field docstrings, and from the YAML options in `conf/`: it is the code's own",
        "description. Set any key on the command line of any tool as `key=value`",
        "(`env.sim_dt=0.005`), or choose a group option as `group=option` (`compute=smoke`).",
        "Allowed values are the checks each section runs before any simulation (one line on",
        "bad input).",
        "",
    ]
    fields_by_section: dict[str, list[FieldDoc]] = {}
    for d in walk(cls):
        section = d.path.rsplit(".", 1)[0] if "." in d.path else "(top level)"
        fields_by_section.setdefault(section, []).append(d)
    for name, sec_cls in sections(cls):
        rows = fields_by_section.get(name, [])
        if not rows:
            continue
        lines += [f"## `{name}`" if name != "(top level)" else "## Top level", ""]
        head = inspect.cleandoc(sec_cls.__doc__ or "")
        if head and not head.startswith(f"{sec_cls.__name__}("):
            lines += [head, ""]
        lines += [
            "| key | type | default | unit | allowed | meaning |",
            "|---|---|---|---|---|---|",
        ]
        for d in rows:
            lines.append(
                f"| `{d.path}` | {_cell(d.type)} | `{_cell(d.default)}` | {_cell(d.unit)} "
                f"| {_cell(d.allowed)} | {_cell(d.doc)} |"
            )
        lines.append("")
    lines += ["## Group options", ""]
    lines += [
        "Each option is a thin YAML in `conf/<group>/`; `group=option` on the command line",
        "applies it. Defaults: `conf/config.yaml`.",
        "",
    ]
    for group in sorted(p for p in conf.iterdir() if p.is_dir() and p.name != "hydra"):
        lines += [f"### `{group.name}`", ""]
        for option in sorted(group.glob("*.yaml")):
            lines += [
                f"#### `{group.name}={option.stem}`",
                "",
                "```yaml",
                option.read_text().rstrip(),
                "```",
                "",
            ]
    return "\n".join(lines) + "\n"
