"""``python -m march.inspect list``: every option a run can name, read from the registries
themselves (never a hand-written list): reward terms with their parameters and needs,
reward options, experiments (``+experiment=``: a comparison arm), student parts with their blocks, student variants and sweeps.

``extra_modules`` and ``hydra.searchpath`` count: a term or part of your module, an arm of your
config tree, is listed like march's own.

Pure data: the env's term modules are imported by name (march.config.terms).
"""

from __future__ import annotations

import dataclasses
import inspect
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from march.config import parts as part_registry
from march.config import terms as term_registry
from march.config.registry import CONF_DIR, SWEEPS_DIR, options


def _value(v: Any) -> str:
    if v is inspect.Parameter.empty:
        return "(required)"
    if isinstance(v, float):
        return f"{v:.4g}"
    text = repr(v)
    return text if len(text) <= 40 else type(v).__name__


def collect(extra_modules: Sequence[str] = (), conf_dirs: Sequence[Path] = ()) -> dict[str, Any]:
    """Everything listable, as plain data."""
    term_registry.import_term_modules(extra_modules)
    part_registry.load_builtin_parts()
    dirs = [CONF_DIR, *conf_dirs]
    terms = {
        name: {
            "params": {k: _value(v) for k, v in spec.parameters().items()},
            "needs": sorted(spec.needs),
            "from": spec.origin,
            "doc": spec.doc,
        }
        for name, spec in sorted(term_registry.TERMS.items())
    }
    rewards = {
        o.name: {
            "label": o.label,
            "terms": sorted(o.data.get("terms") or {}),
            "file": str(o.path),
        }
        for o in options("reward", dirs)
    }
    experiments = {}
    for d in dirs:
        for path in sorted((d / "experiment").glob("*.yaml")):
            data = OmegaConf.to_container(OmegaConf.load(path), resolve=False)
            picks = [x for x in (data.get("defaults") or []) if isinstance(x, dict)]  # type: ignore[union-attr]
            experiments[path.stem] = {
                "sets": [f"{k.split('/')[-1]}={v}" for p in picks for k, v in p.items()]
            }
    parts = {
        kind: {
            name: {
                "block": {f.name: _value(_default(f)) for f in dataclasses.fields(spec.block)}
                if spec.block
                else None,
                "doc": " ".join(spec.doc.split()),
            }
            for name, spec in part_registry.PARTS[kind].items()
        }
        for kind in part_registry.KINDS
    }
    variants = {
        o.name: {k: o.data.get(k, "") for k in ("image", "fusion", "head")} | {"label": o.label}
        for o in options("student", dirs)
    }
    # the repository's sweeps/ and a searchpath tree's sweep/ group (Hydra finds both as +sweep=)
    sweeps = sorted(
        {p.stem for p in SWEEPS_DIR.glob("*.yaml")}
        | {p.stem for d in conf_dirs for p in (Path(d) / "sweep").glob("*.yaml")}
    )
    return {
        "terms": terms,
        "rewards": rewards,
        "experiments": experiments,
        "student_parts": parts,
        "student_variants": variants,
        "sweeps": sweeps,
    }


def _default(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return inspect.Parameter.empty


def render(data: dict[str, Any]) -> str:
    """The listing as text, one option a line."""
    lines = ["reward terms (reward.terms.<name>: weight | {weight, params}):"]
    for name, t in data["terms"].items():
        params = ", ".join(f"{k}={v}" for k, v in t["params"].items()) or "-"
        needs = ",".join(t["needs"]) or "-"
        lines.append(f"  {name:24s} params: {params}  needs: {needs}  [{t['from']}]")
    lines.append("rewards (reward=<name>):")
    for name, a in data["rewards"].items():
        lines.append(f"  {name:24s} {a['label']!r}: {', '.join(a['terms'])}")
    lines.append(
        "experiments (+experiment=<name>: a comparison arm's reward, curriculum and budget together):"
    )
    for name, b in data["experiments"].items():
        lines.append(f"  {name:24s} {' '.join(b['sets'])}")
    lines.append("student parts (student.image | student.fusion | student.head):")
    for kind, names in data["student_parts"].items():
        for name, p in names.items():
            blk = p["block"]
            own = (
                f"  student.parts.{name}: " + ", ".join(f"{k}={v}" for k, v in blk.items())
                if blk
                else ""
            )
            lines.append(f"  {kind}={name:18s}{own}  {p['doc']}")
    lines.append("student variants (student=<name>):")
    for name, v in data["student_variants"].items():
        lines.append(f"  {name:24s} image={v['image']} fusion={v['fusion']} head={v['head']}")
    lines.append("sweeps (-m +sweep=<name>): " + ", ".join(data["sweeps"]))
    return "\n".join(lines)
