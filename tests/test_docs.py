"""The documentation (issue 40): the configuration reference is complete and generated from the
code, the decision log splits into records that keep their numbers, and every shell command of
the getting-started page runs at smoke scale."""

from __future__ import annotations

import dataclasses
import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from march.config import MarchConfig
from march.config import field_docs as fd

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "docs" / "hooks"))
import march_docs  # noqa: E402

# ----------------------------------------------------------------- configuration reference


def test_every_config_field_has_a_docstring():
    assert fd.undocumented(MarchConfig) == []


def test_a_field_without_docstring_is_found():
    @dataclasses.dataclass
    class Inner:
        """A section."""

        a: float = 1.0
        """Documented [m]."""
        b: int = 2

    @dataclasses.dataclass
    class Outer:
        """Top."""

        inner: Inner = dataclasses.field(default_factory=Inner)
        """The section."""
        c: str = "x"

    assert fd.undocumented(Outer) == ["inner.b", "c"]
    rows = {d.path: d for d in fd.walk(Outer)}
    assert rows["inner.a"].unit == "m" and rows["inner.a"].default == "1.0"


def _row(page: str, key: str) -> list[str]:
    line = next(x for x in page.splitlines() if x.startswith(f"| `{key}` |"))
    return [c.strip() for c in line.strip("|").split(" | ")]


def test_reference_has_every_field_with_type_default_unit_and_allowed_values():
    page = fd.render_markdown(MarchConfig)
    keys = [d.path for d in fd.walk(MarchConfig)]
    assert len(keys) > 100
    for key in keys:
        assert f"| `{key}` |" in page, key
    # hand-read from march/config: the values each section's checks allow
    assert _row(page, "compute.name")[4] == "one of `auto`, `cpu`, `gpu`, `smoke`"
    assert _row(page, "seed")[2:5] == ["`0`", "", "[0, 2147483647]"]
    assert _row(page, "compute.dist_timeout_s")[1:5] == ["float", "`300.0`", "s", "> 0"]
    assert _row(page, "depth.fovy")[4] == "(0, 180)"
    assert _row(page, "compute.num_envs")[4] == "> 0"
    # every group option, with its YAML
    for yaml in sorted((REPO / "conf").glob("*/*.yaml")):
        if yaml.parent.name == "hydra":
            continue
        assert f"#### `{yaml.parent.name}={yaml.stem}`" in page
        assert yaml.read_text().rstrip() in page


def test_tools_page_names_every_tool_and_its_arguments():
    page = march_docs.tools_markdown()
    for tool in march_docs.TOOLS:
        assert f"## `python -m {tool}`" in page
    assert "[viewer=video|viser] [port=8080] [steps=N]" in page  # march.play's own arguments
    assert "usage: python -m march.robot policy|sim|selftest" in page
    assert "--se-mode" in page  # analysis/figures.py --help


def test_options_page_lists_every_option_of_the_config_tree_and_registries():
    """The page is built from the registries: every conf/ option, sweep, term and part is on it
    (a new YAML or registered term appears without editing a page)."""
    from march.config import parts, terms

    page = march_docs.options_markdown()
    conf = REPO / "conf"
    for group in ("reward", "experiment", "student"):
        for yaml in (conf / group).glob("*.yaml"):
            assert f"\n  {yaml.stem} " in page, (group, yaml.stem)
    for sweep in (REPO / "sweeps").glob("*.yaml"):
        assert sweep.stem in page.split("sweeps (-m +sweep=<name>):")[1]
    for name in terms.TERMS:
        assert f"\n  {name} " in page
    for kind in parts.KINDS:
        for name in parts.PARTS[kind]:
            assert f"{kind}={name} " in page


# ----------------------------------------------------------------- decision records

LOG = """# Decisions

- **First.** one
  two
- **Second:** three

## A section (issue 1)

Intro text.

- **Alpha.** a
```text
- **not a record** (in a code block)
```
- **Beta.** b
"""


def test_decision_log_splits_into_records_with_stable_addresses():
    recs = march_docs.decision_records(LOG)
    assert [(r["number"], r["title"], r["section"]) for r in recs] == [
        ("1", "First", "Early decisions"),
        ("2", "Second", "Early decisions"),
        ("3", "A section (issue 1): overview", "A section (issue 1)"),
        ("4", "Alpha", "A section (issue 1)"),
        ("5", "Beta", "A section (issue 1)"),
    ]
    assert recs[0]["content"] == "one\ntwo"
    assert "- **not a record**" in recs[3]["content"]
    appended = march_docs.decision_records(LOG + "\n## Later\n\n- **Gamma.** g\n")
    assert [r["file"] for r in appended[:5]] == [r["file"] for r in recs]  # addresses kept
    assert appended[5]["file"] == "gamma.md"
    # a record inserted ABOVE the others moves no address (issue 48: numbered by position, an
    # insertion renumbered every later page)
    inserted = march_docs.decision_records("- **Zeroth.** z\n" + LOG)
    assert [r["file"] for r in inserted[1:]] == [r["file"] for r in recs]
    assert inserted[0]["file"] == "zeroth.md"
    # the same title twice gets its section in front, never a position
    twice = march_docs.decision_records(LOG + "\n## Later\n\n- **Alpha.** again\n")
    assert [r["file"] for r in twice if r["title"] == "Alpha"] == [
        "a-section-issue-1--alpha.md",
        "later--alpha.md",
    ]
    pages = march_docs.decision_pages(LOG)
    assert "- [4. Alpha](alpha.md)" in pages["decisions/index.md"]


def test_the_real_log_keeps_every_decision():
    text = (REPO / "docs" / "decisions.md").read_text()
    recs = march_docs.decision_records(text)
    fence, bullets = False, 0
    for line in text.splitlines():
        fence ^= line.startswith("```")
        bullets += (not fence) and line.startswith("- **")
    assert sum(1 for r in recs if not r["title"].endswith(": overview")) == bullets
    assert len({r["file"] for r in recs}) == len(recs)
    joined = "\n".join(r["content"] for r in recs)
    words = re.findall(r"\w+", text)
    kept = re.findall(r"\w+", joined + " ".join(r["title"] + " " + r["section"] for r in recs))
    assert len(kept) >= 0.97 * len(words)  # the headings' own words are the rest


# ----------------------------------------------------------------- the getting-started page

SESSION_JOB = re.compile(r"^make -C \S+ (smoke|train)\b|^\S*python -m march\.train\b")
"""Commands that may be the session's smoke run (``make smoke``, ``make train`` and
``march.train`` at smoke scale): the test composes each (Hydra's ``--cfg job``, through make where
the page says make) and, where the job is the one the session's ``smoke_run`` fixture ran
(``python -m march.train compute=smoke``, the same config.yaml), puts a copy of that run where the
command would have written it instead of training it again; another job (reward=modelfree)
trains for real. Every block runs in ``make test`` (issue 60)."""


def job_probe(cmd: str) -> str:
    """``cmd`` printing its composed job config instead of running it (make quiet: only the
    YAML on stdout)."""
    if not cmd.startswith("make -C "):
        return f"{cmd} --cfg job"
    _, _, repo, target, *rest = shlex.split(cmd)
    args = [w.removeprefix("ARGS=") for w in rest if w.startswith("ARGS=")]
    quiet = f"make -s --no-print-directory -C {repo} {target}"
    return f"{quiet} {shlex.quote('ARGS=' + ' '.join([*args, '--cfg job']))}"


def session_run_copy(cmd: str, probe_out: str, smoke_run: Path) -> str:
    """Bash for ``cmd``: compose its job into ``probe_out``; the same job as the session's smoke
    run -> a copy of that run under outputs/<date>/<time>_clf_full_smoke_seed0_<pid>-<tag>/ (the
    name and place a run gets), newest in outputs/; another job -> ``cmd`` itself."""
    import yaml

    cfg = yaml.safe_load((smoke_run / "config.yaml").read_text())
    name = f"{cfg['reward']['name']}_{cfg['student']['variant']}_smoke_seed{cfg['seed']}"
    day, clock = "$(date +%Y-%m-%d)", "$(date +%H-%M-%S)"
    dest = f"outputs/{day}/{clock}_{name}_$$-session"
    same_job = REPO / "tests" / "same_job.py"
    same = f"{shlex.quote(sys.executable)} {same_job} {probe_out} {smoke_run / 'config.yaml'}"
    return (
        f"{job_probe(cmd)} > {probe_out}\n"
        f"if {same}; then mkdir -p outputs/{day} && cp -r {smoke_run} {dest}; else {cmd}; fi"
    )


def bash_blocks(page: Path) -> list[str]:
    return re.findall(r"```bash\n(.*?)```", page.read_text(), flags=re.S)


def at_smoke_scale(line: str, tiny_test: str) -> str:
    """A getting-started command as the test runs it: the same command at smoke scale."""
    cmd = line.split("#", 1)[0].rstrip() if not line.lstrip().startswith("cat ") else line
    cmd = re.sub(r"\s+#.*$", "", cmd)
    if not cmd.strip():
        return ""
    if cmd.startswith("make test"):
        cmd = f"make test XDIST= ARGS={tiny_test}"
    if cmd.startswith("make train"):
        cmd = "make train ARGS=compute=smoke"
    if cmd.startswith("make "):  # make runs in the checkout (its .venv, outputs/, site/)
        return f"make -C {REPO} {cmd[5:]}"
    if re.match(r"^(\S*/)?pip install", cmd):
        return cmd.replace("pip install", "pip install --dry-run --no-deps --quiet", 1)
    if re.match(r"^(\S*/)?pytest", cmd):
        return f"{cmd} -p no:xdist {tiny_test}".replace("-n auto --dist loadfile ", "")
    if "march.train" in cmd:
        cmd = re.sub(r"compute=\w+", "compute=smoke", cmd)
        return cmd if "compute=smoke" in cmd else f"{cmd} compute=smoke"
    return cmd


def _workdir(tmp: Path) -> Path:
    """A scratch directory that sees the repository (links to its top-level entries), so that
    the files the commands name (env.json, plan.png) land there, not in the checkout; ``make``
    runs in the checkout itself (``-C``: its .venv is never reinstalled from a link), and
    outputs/ is the checkout's (git-ignored)."""
    work = tmp / "work"
    work.mkdir()
    (REPO / "outputs").mkdir(exist_ok=True)
    for entry in REPO.iterdir():
        if entry.name not in (".git", "site") and not entry.name.endswith((".png", ".json")):
            (work / entry.name).symlink_to(entry)
    return work


BLOCKS = bash_blocks(REPO / "docs" / "getting-started.md")
TINY_TEST = "tests/test_hlip.py"


def test_getting_started_has_cpu_and_gpu_commands():
    text = "\n".join(BLOCKS)
    # make docs: CI builds the site only here (.ci/run)
    for needed in (
        "make install",
        "make test",
        "make docs",
        "make smoke",
        "march.play",
        "make train",
    ):
        assert needed in text
    assert "compute=gpu" in text
    assert (
        at_smoke_scale("make train   # x", TINY_TEST) == f"make -C {REPO} train ARGS=compute=smoke"
    )
    assert (
        at_smoke_scale(".venv/bin/python -m march.train compute=gpu seed=1", TINY_TEST)
        == ".venv/bin/python -m march.train compute=smoke seed=1"
    )


@pytest.mark.parametrize("block", [pytest.param(b, id=f"block{i}") for i, b in enumerate(BLOCKS)])
def test_getting_started_block_runs_at_smoke_scale(block, tmp_path, request):
    work = _workdir(tmp_path)
    script, commands = ["set -euo pipefail"], []
    for i, line in enumerate(block.splitlines()):
        cmd = at_smoke_scale(line, TINY_TEST)
        if not cmd:
            continue
        commands.append(cmd)
        if SESSION_JOB.match(cmd) and "--cfg" not in cmd:
            smoke_run = request.getfixturevalue("smoke_run")
            cmd = session_run_copy(cmd, str(tmp_path / f"job{i}.yaml"), smoke_run)
        script.append(cmd)
    env = {
        **os.environ,
        "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}",
        "WANDB_MODE": "offline",
    }
    proc = subprocess.run(
        ["bash", "-c", "\n".join(script)],
        cwd=work,
        env=env,
        capture_output=True,
        text=True,
        timeout=1800,
    )
    assert proc.returncode == 0, "\n".join(script) + "\n" + (proc.stdout + proc.stderr)[-3000:]
    for cmd in commands:  # the files the commands name were written
        for word in shlex.split(cmd):
            if word.startswith("out=") and "$" not in word:
                assert (work / word[4:]).stat().st_size > 0, cmd
        if ">" in cmd:
            target = work / cmd.rsplit(">", 1)[1].strip()
            assert target.stat().st_size > 0, cmd
            if target.suffix == ".json":
                json.loads(target.read_text())
