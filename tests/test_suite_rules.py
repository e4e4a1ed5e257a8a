"""Rules the test suite keeps so that it passes on any day (issue 48). No wall-clock assertion:
a test that compares a measured duration (the difference of two clock readings) with a fixed
number fails on a loaded machine (``assert time.time() - t0 < 60`` took 90 s at load 15). What
such a test means is asserted through an observable instead (no env built, nothing compiled, no
file written, the timeout named in the error); durations go to ``march.bench`` or the docs.

Allowed: a hang guard that compares a clock reading with a deadline read from the same clock
(``while time.time() < deadline``), a ``timeout=`` argument, and printing a duration."""

from __future__ import annotations

import ast
import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent
ROOT = TESTS.parent

CLOCKS = {"time", "perf_counter", "monotonic", "process_time", "thread_time", "default_timer"}
CLOCKS |= {f"{c}_ns" for c in CLOCKS}
CASTS = {"float", "int", "round", "abs"}  # a duration wrapped in one is still a duration


def _is_clock_call(node: ast.AST) -> bool:
    """``time.time()``, ``time.perf_counter()``, ``perf_counter()`` (imported by name),
    ``timeit.default_timer()``..."""
    if not isinstance(node, ast.Call):
        return False
    f = node.func
    name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""
    return name in CLOCKS and not node.args


FUNCTIONS = ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda


def _walk_scope(root: ast.AST):
    """Every node of one function (or the module) without those of the functions inside it:
    a name means one thing per function."""
    todo = list(ast.iter_child_nodes(root))
    while todo:
        node = todo.pop()
        yield node
        if not isinstance(node, FUNCTIONS):
            todo.extend(ast.iter_child_nodes(node))


ASSIGNS = ast.Assign | ast.AnnAssign | ast.AugAssign


def _assigned(a: ast.Assign | ast.AnnAssign | ast.AugAssign) -> set[str]:
    """The names an assignment binds (``t0``, ``t0, t1``)."""
    targets = a.targets if isinstance(a, ast.Assign) else [a.target]
    return {n.id for t in targets for n in ast.walk(t) if isinstance(n, ast.Name)}


class _Scope:
    """One function's (or the module's) names: which hold a clock reading (or a deadline made
    from one), which a duration (a difference of two readings); a function inside another sees
    the names of the one around it."""

    def __init__(self, body: ast.AST, outer: _Scope | None = None):
        assigns = [n for n in _walk_scope(body) if isinstance(n, ASSIGNS)]
        own = set().union(*map(_assigned, assigns))  # a local name hides the outer one
        self.readings: set[str] = set(outer.readings) - own if outer else set()
        self.durations: set[str] = set(outer.durations) - own if outer else set()
        for _ in range(3):  # names assigned from names assigned from a clock
            for a in assigns:
                targets = a.targets if isinstance(a, ast.Assign) else [a.target]
                names = {t.id for t in targets if isinstance(t, ast.Name)}
                for t in targets:  # t0, t1 = time.time(), time.time()
                    if isinstance(t, ast.Tuple) and isinstance(a.value, ast.Tuple):
                        for tt, v in zip(t.elts, a.value.elts, strict=False):
                            if isinstance(tt, ast.Name):
                                self._classify({tt.id}, v)
                if a.value is not None:
                    self._classify(names, a.value)

    def _classify(self, names: set[str], value: ast.AST) -> None:
        if self.is_duration(value):
            self.durations |= names
        elif self.has_reading(value):
            self.readings |= names

    def has_reading(self, node: ast.AST) -> bool:
        return any(
            _is_clock_call(n)
            or (isinstance(n, ast.Name) and n.id in self.readings | self.durations)
            for n in ast.walk(node)
        )

    def is_reading(self, node: ast.AST) -> bool:
        return _is_clock_call(node) or (isinstance(node, ast.Name) and node.id in self.readings)

    def is_duration(self, node: ast.AST) -> bool:
        if isinstance(node, ast.Name):
            return node.id in self.durations
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Sub):
            return self.is_reading(node.left) and self.is_reading(node.right)
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Mult | ast.Div):
            return self.is_duration(node.left) or self.is_duration(node.right)  # in ms, per step
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name):
            return node.func.id in CASTS and any(self.is_duration(a) for a in node.args)
        return False


def _zero(node: ast.AST) -> bool:
    """``0``: a sign check (``deadline - time.time() > 0`` is a hang guard), no time budget."""
    return isinstance(node, ast.Constant) and node.value == 0


def timed_assertions(source: str, filename: str = "<test>") -> list[str]:
    """``file:line: text`` of every comparison of a measured duration with something that is no
    clock reading (a number, a name such as ``timeout_s + 30``)."""
    tree = ast.parse(source, filename)
    found = set()
    todo: list[tuple[ast.AST, _Scope | None]] = [(tree, None)]
    while todo:
        body, outer = todo.pop()
        scope = _Scope(body, outer)
        for node in _walk_scope(body):
            if isinstance(node, FUNCTIONS):
                todo.append((node, scope))
            if not isinstance(node, ast.Compare):
                continue
            sides = [node.left, *node.comparators]
            fixed = [s for s in sides if not scope.has_reading(s)]
            if any(scope.is_duration(s) for s in sides) and any(not _zero(s) for s in fixed):
                found.add((node.lineno, ast.get_source_segment(source, node) or ""))
    return [f"{filename}:{line}: {text}" for line, text in sorted(found)]


def test_no_test_compares_a_measured_duration_with_a_fixed_number():
    files = sorted(TESTS.rglob("*.py"))
    assert len(files) > 50 and Path(__file__) in files  # the rule reads the whole suite
    found = [
        hit
        for f in files
        for hit in timed_assertions(f.read_text(), f.relative_to(TESTS.parent).as_posix())
    ]
    assert found == [], "wall-clock assertions (assert an observable instead):\n" + "\n".join(found)


TIMED = [
    "assert time.time() - t0 < 60",  # the one that failed at load 15
    "assert time.perf_counter() - t0 <= 5.0",
    "assert 60 > time.monotonic() - t0",
    "seconds = time.time() - t0\nassert seconds <= 600",
    "took = float(time.perf_counter() - t0)\nassert took < 1",
    "waited = time.time() - killed\nassert waited < timeout_s + 30",
    "t1 = time.time()\nassert t1 - t0 < 2",
    "assert (time.time() - t0) * 1000 < 50  # ms",
    "assert 2.5 < round(time.time() - t0, 1) < 15",
    "assert perf_counter() - start < LIMIT",
    "assert timeit.default_timer() - t0 < 3",
    "assert time.monotonic_ns() - t0 < 10**9",
    "elapsed = time.time() - t0\nok = elapsed < 60\nassert ok",
    "total = 0.0\ntotal += time.time() - t0\nassert total < 9",
    "def inner():\n    assert time.time() - t0 < 5\ninner()",  # t0 from the function around
]
ALLOWED = [
    "deadline = time.time() + 600\nwhile time.time() < deadline:\n    pass",
    "assert time.time() < deadline, 'no checkpoint after 600 s'",
    "took = time.time() - t0\nprint(f'{took:.1f} s')",
    "proc.communicate(timeout=60)",
    "assert t_sim - t_start < 60",  # simulated time, no clock call
    "assert time.time() - t0 >= time.time() - t1",  # two durations, no fixed number
    "deadline = time.time() + 5\nwhile deadline - time.time() > 0:\n    pass",  # a sign check
    "assert elapsed < 60",  # a name not from a clock (a controller's elapsed seconds)
    "def other():\n    took = 3\n    assert took < 5",  # a name of its own
]


@pytest.mark.parametrize("body", TIMED)
def test_the_rule_finds_a_timed_assertion(body):
    lines = body.splitlines()
    source = "import time, timeit\nfrom time import perf_counter\n\n\ndef test_x():\n"
    source += "    t0 = start = killed = time.time()\n"
    source += "".join(f"    {ln}\n" for ln in lines)
    assert len(timed_assertions(source)) == 1, source


@pytest.mark.parametrize("body", ALLOWED)
def test_the_rule_leaves_hang_guards_and_reports_alone(body):
    source = "import time\n\n\ndef test_x():\n    t0 = t1 = time.time()\n"
    source += "    took = time.time() - t0\n"  # the same name, a duration in the outer function
    source += "".join(f"    {ln}\n" for ln in body.splitlines())
    assert timed_assertions(source) == [], source


def test_the_rule_reads_a_planted_test_file(tmp_path):
    """The suite's check, run on a copy of a real test file with the assertion that failed on a
    loaded machine planted back into it."""
    real = (TESTS / "test_run_dir.py").read_text()
    assert timed_assertions(real) == []
    planted = real + "\n\ndef test_planted(tmp_path):\n    t0 = time.time()\n"
    planted += "    assert time.time() - t0 < 60 and not tmp_path.exists()\n"
    (tmp_path / "test_planted.py").write_text(planted)
    hits = timed_assertions((tmp_path / "test_planted.py").read_text(), "test_planted.py")
    assert len(hits) == 1 and hits[0].endswith("time.time() - t0 < 60"), hits


# ------------------------------------------------------------- docs: strict for real (item 4)

DOC_PATH = re.compile(r"\bdocs/[\w./-]*\w\.(?:py|md|yml|png|svg|css|js)\b")
NAMING = ["march/**/*.py", "tests/*.py", "scripts/*.py", "Makefile", "README.md", "mkdocs.yml"]


def doc_paths(text: str) -> set[str]:
    """Every ``docs/...`` file a text names."""
    return set(DOC_PATH.findall(text))


def test_every_docs_file_the_code_points_to_exists():
    named = {
        (path, f.relative_to(ROOT).as_posix())
        for pattern in NAMING
        for f in ROOT.glob(pattern)
        if f != Path(__file__)  # it names a dead pointer on purpose, below
        for path in doc_paths(f.read_text())
    }
    assert len(named) > 20  # the pointers are read at all
    assert [n for n in sorted(named) if not (ROOT / n[0]).exists()] == []


def test_a_dead_docs_pointer_is_found():
    """The one issue 48 found, march/config/field_docs.py naming ``docs/hooks.py``."""
    text = "The mkdocs hook (``docs/hooks.py``) writes it; see docs/hooks/march_docs.py."
    assert doc_paths(text) == {"docs/hooks.py", "docs/hooks/march_docs.py"}
    assert not (ROOT / "docs/hooks.py").exists() and (ROOT / "docs/hooks/march_docs.py").exists()


def test_the_docs_build_fails_on_a_broken_anchor():
    """``make docs`` (what CI runs) is strict for real: anchors are validated at ``warn``, which
    ``--strict`` makes an error, and the build runs without ``--quiet`` (mkdocs 1.6 drops
    warnings before its strict count then) and without ``-v`` (which skips anchor checks)."""
    config = (ROOT / "mkdocs.yml").read_text()
    after = config.split("\nvalidation:\n", 1)[1].splitlines()
    block = after[: next(i for i, ln in enumerate(after) if not ln.startswith(" "))]
    levels = dict(ln.strip().split(": ", 1) for ln in block if ": " in ln)
    assert levels.get("anchors") == "warn" and "info" not in levels.values(), levels
    recipe = (ROOT / "Makefile").read_text().split("\ndocs:", 1)[1].split("\n\n")[0]
    build = next(ln for ln in recipe.splitlines() if ln.startswith("\t") and "mkdocs build" in ln)
    flags = build.split("mkdocs build", 1)[1].split()
    assert "--strict" in flags and not {"--quiet", "-q", "--verbose", "-v"} & set(flags), build


# -- programs the project does not install (issue 60) -------------------------------------------


def test_programs_the_project_does_not_install_are_hidden_from_every_test():
    """In the suite neither shutil.which nor a process a test starts finds srun, sbatch, ffmpeg
    or a browser, also on a machine where they are installed: a test that needs one fails
    everywhere, not only on a newcomer's machine (conftest.NOT_INSTALLED)."""
    from conftest import NOT_INSTALLED

    assert {"srun", "sbatch", "ffmpeg", "chromium"} <= set(NOT_INSTALLED)
    assert [p for p in NOT_INSTALLED if shutil.which(p)] == []
    names = " ".join(NOT_INSTALLED)
    out = subprocess.run(
        ["bash", "-c", f"for p in {names}; do command -v $p; done; command -v sh"],
        capture_output=True,
        text=True,
    )
    assert out.stdout.split() == [shutil.which("sh")], out.stdout


def test_a_planted_srun_is_hidden_and_the_rest_of_its_folder_kept(tmp_path):
    """A Slurm machine's /usr/bin (srun beside sh), a venv's bin/ (python): srun goes, sh and the
    venv's folder stay as they are."""
    from conftest import NOT_INSTALLED, hidden_path

    usr, venv = tmp_path / "usr_bin", tmp_path / "venv_bin"
    for folder, names in ((usr, ("srun", "sbatch", "sh")), (venv, ("python",))):
        folder.mkdir()
        for name in names:
            (folder / name).write_text("#!/bin/sh\n")
            (folder / name).chmod(0o755)
    path = os.pathsep.join([str(venv), str(usr)])
    assert shutil.which("srun", path=path) == str(usr / "srun")  # the plant is found without
    hidden = hidden_path(path, NOT_INSTALLED, tmp_path / "shadow")
    assert shutil.which("srun", path=hidden) is None
    assert shutil.which("sbatch", path=hidden) is None
    assert Path(shutil.which("sh", path=hidden)).resolve() == usr / "sh"
    assert hidden.split(os.pathsep)[0] == str(venv)


@pytest.mark.needs_program("srun", "sbatch")
def test_a_test_marked_needs_program_gets_the_real_path():
    """Where Slurm is installed (``make test-slurm``) this runs and sees srun; elsewhere it is
    skipped with one line naming the make target."""
    assert shutil.which("srun") and shutil.which("sbatch")
