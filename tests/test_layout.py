"""The package's layout as a newcomer reads it (issue 14): rooms named after the paper's stages
and the harness's tools, imports that flow one way, pure mathematics free of the simulator, no
same-named modules, and ``docs/layout.md`` naming every room.

One idea per module (issue 54; the 500-line cap of 2026-11-30 is retired: it bent the design,
splitting ideas across files that then traded private names and imported each other in circles):
every module of ``march/`` and ``analysis/`` has a docstring naming its idea, no module imports a
private (``_name``) from another module, and no import circle exists between modules, inside a
room or between rooms. The checkers below take any source tree, so their own planted faults (a
private import, a two-file circle, a module without a docstring) are tested on a temporary one.

The import graph is read from the source (``ast``), including imports inside functions and
``if TYPE_CHECKING:`` blocks, so a lazy or type-only import cannot hide a dependency.
"""

from __future__ import annotations

import ast
import json
import re
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "march"

LAYERS: dict[str, int] = {
    # the shared error type every layer may raise for bad input
    "errors": 0,
    # torch.compile of pure maths (compute.compile_math): torch only
    "compiled_math": 0,
    # strict JSON for every file march writes (null for undefined values): plain Python
    "strict_json": 0,
    # random numbers keyed by (seed, rollout, draw) (an evaluation's streams): torch only
    "keyed_random": 0,
    # the one statistics module (t interval, Fieller, verdicts): numpy / scipy only
    "stats": 0,
    # stage 0-2 mathematics: plain numpy / torch
    "world": 1,
    "reference": 2,
    "clf": 2,
    # the typed config (Hydra -> dataclasses) and the one bridge to mjlab
    "config": 3,
    "env": 4,
    # what lives on disk: run directories, locks, status, checkpoints, bundles (the one gate
    # every tool reads them through; no simulator)
    "store": 5,
    # networks, runners, the shared evaluation protocol
    "policies": 5,
    "learn": 6,
    "evaluation": 7,
    # tools: each a module or a subpackage with __main__, none importing another
    "train": 8,
    "inspect": 8,
    "play": 8,
    "bench": 8,
    "viz": 8,
    "export": 8,
    "sim2sim": 8,
    "audit": 8,
    # the robot loop over DDS builds on the sim-to-sim loop (same bundle, observation and
    # action path; its self-test runs sim2sim in-process), so it sits one layer above the tools
    "robot": 9,
}
"""Every room of ``march/`` and its layer: a module imports only its own room and lower layers."""

PURE = ("world", "reference", "clf")
"""Rooms of plain mathematics: no simulator (mjlab, MuJoCo, warp) and no config framework."""
SIMULATOR = ("mjlab", "mujoco", "mujoco_warp", "warp")
TOOLS = {
    "march.train": "march/train.py",
    "march.inspect": "march/inspect.py",
    "march.play": "march/play.py",
    "march.bench": "march/bench/__main__.py",
    "march.viz": "march/viz/__main__.py",
    "march.export": "march/export/__main__.py",
    "march.sim2sim": "march/sim2sim/__main__.py",
    "march.robot": "march/robot/__main__.py",
    "march.audit": "march/audit/__main__.py",
}
"""The ``python -m`` commands of the README and the file each one runs."""


def _modules(base: Path) -> list[Path]:
    return sorted(p for p in base.rglob("*.py") if "__pycache__" not in p.parts)


def _room(module: str) -> str:
    """``march.reference.planner`` -> ``reference``; ``march.train`` -> ``train``; the package
    itself (``march/__init__.py``: a docstring and a version) -> ``""``."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def _dotted(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _march_imports(path: Path) -> set[str]:
    """Every ``march.*`` module ``path`` imports, at any depth of the file."""
    here = _dotted(path)
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name.startswith("march.")}
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against this module's package
                pkg = here.split(".")
                if path.name != "__init__.py":
                    pkg = pkg[:-1]
                base = ".".join(pkg[: len(pkg) - node.level + 1])
                found.add(f"{base}.{node.module}" if node.module else base)
            elif node.module and node.module.startswith("march."):
                found.add(node.module)
    return found


def _graph() -> dict[str, set[str]]:
    return {_dotted(p): _march_imports(p) for p in _modules(PACKAGE)}


def test_every_room_has_a_layer():
    rooms = {_room(m) for m in _graph() if m != "march"}
    assert rooms == set(LAYERS), f"unplaced rooms: {rooms ^ set(LAYERS)}"


def test_imports_flow_one_way():
    """No module imports a higher layer or another tool; within a room anything goes."""
    wrong = []
    for module, imports in _graph().items():
        if module == "march":
            continue
        src = _room(module)
        for target in imports:
            dst = _room(target)
            if dst == src:
                continue
            if LAYERS[dst] > LAYERS[src] or (LAYERS[dst] == LAYERS[src] >= LAYERS["train"]):
                wrong.append(f"{module} -> {target}")
    assert wrong == []


def test_no_import_cycles_between_rooms():
    rooms: dict[str, set[str]] = defaultdict(set)
    for module, imports in _graph().items():
        if module != "march":
            rooms[_room(module)] |= {_room(t) for t in imports} - {_room(module)}
    state: dict[str, int] = {}

    def visit(room: str, trail: list[str]) -> None:
        if state.get(room) == 1:
            pytest.fail("cycle: " + " -> ".join([*trail, room]))
        if state.get(room) == 2:
            return
        state[room] = 1
        for nxt in sorted(rooms[room]):
            visit(nxt, [*trail, room])
        state[room] = 2

    for room in sorted(rooms):
        visit(room, [])


def test_pure_mathematics_imports_no_simulator():
    """Importing every module of the pure rooms in a fresh interpreter loads no simulator and no
    Hydra: they run anywhere torch runs."""
    mods = [_dotted(p) for p in _modules(PACKAGE) if _room(_dotted(p)) in PURE]
    assert len(mods) >= 6  # courses, footholds, hlip, planner, trajectory, lyapunov at least
    code = "import importlib, json, sys\n"
    code += "".join(f"importlib.import_module({m!r})\n" for m in mods)
    code += "print(json.dumps(sorted(sys.modules)))\n"
    res = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300
    )
    assert res.returncode == 0, res.stderr[-2000:]
    loaded = json.loads(res.stdout)
    bad = sorted(m for m in loaded if m.split(".")[0] in (*SIMULATOR, "hydra", "omegaconf"))
    assert bad == []
    outside = sorted(
        m
        for m in loaded
        if m.startswith("march.")
        and _room(m) not in (*PURE, "errors", "compiled_math", "keyed_random")
    )
    assert outside == []


def test_module_names_are_unique():
    names: dict[str, list[str]] = defaultdict(list)
    for path in _modules(PACKAGE) + _modules(ROOT / "analysis"):
        rel = str(path.relative_to(ROOT))
        if path.name not in ("__init__.py", "__main__.py"):
            names[path.stem].append(rel)
    assert {k: v for k, v in names.items() if len(v) > 1} == {}


# ------------------------------------------------------------------ one idea per module


def _sources(root: Path, packages: tuple[str, ...]) -> dict[str, Path]:
    """Dotted module name -> file, for every module of ``packages`` under ``root``."""
    out = {}
    for pkg in packages:
        for path in _modules(root / pkg):
            parts = path.relative_to(root).with_suffix("").parts
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def _imported_names(path: Path, module: str, known: set[str]) -> list[tuple[str, str | None]]:
    """(module, name) pairs ``path`` imports at any depth (name None: the module itself). A
    ``from pkg import x`` where ``pkg.x`` is a module imports that module."""
    out: list[tuple[str, str | None]] = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out += [(a.name, None) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: resolve against this module's package
                pkg = module.split(".")
                if path.name != "__init__.py":
                    pkg = pkg[:-1]
                pkg = pkg[: len(pkg) - node.level + 1]
                base = ".".join([*pkg, base] if base else pkg)
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                out.append((sub, None) if sub in known else (base, alias.name))
    return out


def private_imports(root: Path, packages: tuple[str, ...]) -> list[str]:
    """``importer -> module._name`` for every private name imported from another module (a
    dunder such as ``__version__`` is not private)."""
    mods = _sources(root, packages)
    wrong = []
    for module, path in mods.items():
        for target, name in _imported_names(path, module, set(mods)):
            if target in mods and target != module:
                private = name is not None and name.startswith("_") and not name.startswith("__")
                if private:
                    wrong.append(f"{module} -> {target}.{name}")
    return sorted(wrong)


def import_circles(root: Path, packages: tuple[str, ...]) -> list[list[str]]:
    """Every set of modules that import each other in a circle (the strongly connected
    components of the module import graph with more than one module), each sorted."""
    mods = _sources(root, packages)
    graph = {
        m: sorted({t for t, _ in _imported_names(p, m, set(mods)) if t in mods and t != m})
        for m, p in mods.items()
    }
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    found: list[list[str]] = []

    def connect(v: str) -> None:  # Tarjan's algorithm
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            connect(v)
    return sorted(found)


def undocumented_modules(root: Path, packages: tuple[str, ...]) -> list[str]:
    """Modules whose docstring does not name an idea (none, or fewer than three words)."""
    out = []
    for module, path in _sources(root, packages).items():
        doc = ast.get_docstring(ast.parse(path.read_text())) or ""
        if len(doc.split()) < 3:
            out.append(module)
    return sorted(out)


HOUSE = ("march", "analysis")
"""The trees the one-idea rules read."""


def test_no_module_imports_a_private_name_from_another():
    assert private_imports(ROOT, HOUSE) == []


def test_no_import_circle_between_modules():
    """Inside a room or between rooms: a module that needs another's name and is needed back
    holds two halves of one idea (join them) or a shared part (give it its own module)."""
    assert import_circles(ROOT, HOUSE) == []


def test_every_module_docstring_names_its_idea():
    assert undocumented_modules(ROOT, HOUSE) == []


def _tree(tmp: Path, files: dict[str, str]) -> Path:
    for rel, text in files.items():
        path = tmp / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return tmp


DOC = '"""One idea, named here."""\n'


def test_the_rules_catch_their_planted_faults(tmp_path):
    """The checkers themselves, on a planted tree: a private name imported from a sibling
    (also relatively and lazily), a two-file circle (one side a type-only import), a module
    without a docstring; the clean modules beside them pass."""
    root = _tree(
        tmp_path,
        {
            "pkg/__init__.py": DOC,
            "pkg/clean.py": DOC + "from pkg.shared import PUBLIC\nfrom pkg import shared\n",
            "pkg/shared.py": DOC + "PUBLIC = 1\n_HIDDEN = 2\n__version__ = '0'\n",
            "pkg/peek.py": DOC + "from pkg.shared import PUBLIC, _HIDDEN\n",
            "pkg/lazy.py": DOC + "def f():\n    from .shared import _HIDDEN\n    return _HIDDEN\n",
            "pkg/dunder.py": DOC + "from pkg.shared import __version__\n",
            "pkg/left.py": DOC + "from pkg.right import R\nL = 1\n",
            "pkg/right.py": DOC
            + "from typing import TYPE_CHECKING\nR = 2\nif TYPE_CHECKING:\n"
            + "    from pkg.left import L\n",
            "pkg/mute.py": "X = 1\n",
            "pkg/terse.py": '"""Helpers."""\n',
        },
    )
    assert private_imports(root, ("pkg",)) == [
        "pkg.lazy -> pkg.shared._HIDDEN",
        "pkg.peek -> pkg.shared._HIDDEN",
    ]
    assert import_circles(root, ("pkg",)) == [["pkg.left", "pkg.right"]]
    assert undocumented_modules(root, ("pkg",)) == ["pkg.mute", "pkg.terse"]
    # the rules on the clean part alone: nothing found
    for bad in ("peek", "lazy", "left", "right", "mute", "terse"):
        (root / "pkg" / f"{bad}.py").unlink()
    assert private_imports(root, ("pkg",)) == []
    assert import_circles(root, ("pkg",)) == []
    assert undocumented_modules(root, ("pkg",)) == []


def test_every_readme_tool_is_a_runnable_module():
    readme = (ROOT / "README.md").read_text()
    commands = set(re.findall(r"python -m (march(?:\.\w+)+)", readme))
    assert commands == set(TOOLS), commands ^ set(TOOLS)
    for tool, path in TOOLS.items():
        source = (ROOT / path).read_text()
        assert "main(" in source, f"{tool}: {path} does not run a main"


def test_docs_layout_names_every_room():
    """``docs/layout.md`` has one line per package and per module of march/ and analysis/."""
    text = (ROOT / "docs" / "layout.md").read_text()
    missing = []
    for path in _modules(PACKAGE) + _modules(ROOT / "analysis"):
        rel = path.relative_to(ROOT)
        if path.name == "__main__.py":
            continue
        name = f"{rel.parent}/" if path.name == "__init__.py" else str(rel)
        if f"`{name}`" not in text:
            missing.append(name)
    assert missing == []


def _runtime_imports(path: Path) -> set[str]:
    """Top-level package names ``path`` imports when it runs (``if TYPE_CHECKING:`` blocks,
    read only by type checkers, left out)."""
    tree = ast.parse(path.read_text())
    skip: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            skip |= {id(n) for stmt in node.body for n in ast.walk(stmt)}
    found = set()
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            found |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            found.add(node.module.split(".")[0])
    return found


def test_only_the_env_imports_mjlab():
    """``march/env/`` is the one door to mjlab: the runners, the evaluation, the tools reach
    mjlab's envs, wrappers, robot and renderer through it."""
    users = sorted(
        str(p.relative_to(ROOT))
        for p in _modules(PACKAGE)
        if "mjlab" in _runtime_imports(p) and _room(_dotted(p)) != "env"
    )
    assert users == []
    assert any("mjlab" in _runtime_imports(p) for p in _modules(PACKAGE / "env"))
