"""march's term table (march.config.term_table): a config is checked against march's own reward
terms without importing the simulator, and the table says what the registry says (issue 60)."""

from __future__ import annotations

import json
import pprint
import subprocess
import sys
from pathlib import Path

import pytest

from march.config import ConfigError
from march.config import terms as registry
from march.config.cli import load
from march.config.term_table import BUILTIN_TERMS

ROOT = Path(__file__).resolve().parent.parent


def _real_builtins() -> dict[str, registry.TermSpec]:
    """march's own terms as their module registers them (imported here)."""
    registry.import_term_modules()
    return {n: registry.TERMS[n] for n in BUILTIN_TERMS}


def test_the_table_is_what_the_registry_registers():
    """In a fresh process (no term of another test registered): every term march.env.rewards
    registers, as table entries, is the table."""
    code = (
        "import json\n"
        "from march.config import terms\n"
        "terms.import_term_modules()\n"
        "print(json.dumps({n: terms.table_entry(s) for n, s in sorted(terms.TERMS.items())}))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stderr[-2000:]
    real = json.loads(out.stdout.splitlines()[-1])
    assert real == BUILTIN_TERMS, (
        "march's reward terms changed: march/config/term_table.py is now\nBUILTIN_TERMS = "
        + pprint.pformat(real, width=96, sort_dicts=False)
    )


CASES = [
    ["+reward.terms.bogus=1"],
    ["+reward.terms.upright={weight: 1, params: {sd: 2}}"],
    ["+reward.terms.clf={weight: 1, params: {command_name: ref, x: 1}}"],
    ["reward=modelfree", "+reward.terms.foot_slip={weight: 1, params: {bogus: 1}}"],
    ["reward=modelfree", "reward.terms.alive=2"],
    ["+reward.terms.upright={weight: 1, params: {std: 0.1}}"],
]


@pytest.mark.parametrize("overrides", CASES, ids=[str(i) for i in range(len(CASES))])
def test_a_config_is_refused_or_passed_alike_by_the_table_and_the_functions(overrides, monkeypatch):
    """The same line (or none) from the table's entries as from the imported functions."""
    reward = load(overrides).reward
    real = _real_builtins()
    table = {n: registry.from_table(n, e) for n, e in BUILTIN_TERMS.items()}
    said, needs = [], []
    for specs in (real, table):
        monkeypatch.setattr(registry, "TERMS", dict(specs))
        try:
            registry.check_reward(reward)
            said.append(None)
        except ConfigError as err:
            said.append(str(err))
        needs.append(registry.needs(reward))
    assert said[0] == said[1]
    assert needs[0] == needs[1]
    assert (said[0] is None) == (overrides in (CASES[4], CASES[5])), said[0]


def test_a_refused_term_imports_no_simulator():
    """A tool's config check (the terms included) in a fresh process: the refusal is the
    registry's line and neither mjlab nor warp nor mujoco is imported."""
    code = (
        "import sys\n"
        "from march.config.cli import load\n"
        "from march.config.terms import check_terms\n"
        "try:\n"
        "    check_terms(load(['+reward.terms.upright={weight: 1, params: {sd: 2}}']))\n"
        "except Exception as err:\n"
        "    print(err)\n"
        "check_terms(load(['reward=modelfree']))\n"
        "print(sorted(m for m in ('mjlab', 'mujoco_warp', 'warp', 'mujoco') if m in sys.modules))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, out.stderr[-2000:]
    refusal, imported = out.stdout.strip().splitlines()
    assert refusal.startswith("reward.terms.upright.params: ['sd'] not parameter(s) of "), refusal
    assert "its parameters: std, body_names" in refusal
    assert imported == "[]"


def test_the_env_replaces_the_table_entries_with_the_functions(monkeypatch):
    """Table entries first, then march's functions registered (what importing its term module
    does): each entry becomes its function, none is refused as a name taken."""
    real = _real_builtins()
    table = {n: registry.from_table(n, e) for n, e in BUILTIN_TERMS.items()}
    monkeypatch.setattr(registry, "TERMS", table)
    for name, spec in real.items():
        registry.register_term(name, spec.func, spec.params, spec.needs)
    assert registry.TERMS == real
