"""The package's layout as a newcomer reads it (issue 14): rooms named after the paper's stages
and the harness's tools, imports that flow one way, pure mathematics free of the simulator, no
oversized or same-named modules, and ``docs/layout.md`` naming every room.

The import graph is read from the source (``ast``), including imports inside functions, so a
lazy import cannot hide a dependency that points the wrong way.
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
MAX_LINES = 500
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
        if m.startswith("march.") and _room(m) not in (*PURE, "errors", "compiled_math")
    )
    assert outside == []


def test_module_names_are_unique_and_modules_small():
    names: dict[str, list[str]] = defaultdict(list)
    big = []
    for path in _modules(PACKAGE) + _modules(ROOT / "analysis"):
        rel = str(path.relative_to(ROOT))
        if path.name not in ("__init__.py", "__main__.py"):
            names[path.stem].append(rel)
        lines = len(path.read_text().splitlines())
        if lines > MAX_LINES:
            big.append(f"{rel}: {lines}")
    assert {k: v for k, v in names.items() if len(v) > 1} == {}
    assert big == []


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
