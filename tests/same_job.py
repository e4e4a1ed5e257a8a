"""``python tests/same_job.py <job.yaml> <run>/config.yaml``: exit 0 when the job config a command
composed (Hydra's ``--cfg job``) is the config a run used, else 1 naming the first keys that
differ (tests/test_docs.py: a getting-started command that is the session's smoke run)."""

from __future__ import annotations

import sys
from typing import Any

import yaml


def differences(a: Any, b: Any, where: str = "") -> list[str]:
    """The dotted keys whose values differ between two parsed YAML documents."""
    if isinstance(a, dict) and isinstance(b, dict):
        out: list[str] = []
        for key in sorted(set(a) | set(b), key=str):
            missing = "<absent>"
            out += differences(a.get(key, missing), b.get(key, missing), f"{where}.{key}")
        return out
    return [] if a == b else [f"{where.lstrip('.')}: {a!r} != {b!r}"]


def main(job: str, run_config: str) -> int:
    with open(job) as f, open(run_config) as g:
        diff = differences(yaml.safe_load(f), yaml.safe_load(g))
    if diff:
        print(f"not the session's run ({len(diff)} keys differ): {diff[:3]}", file=sys.stderr)
    return 1 if diff else 0


if __name__ == "__main__":
    raise SystemExit(main(*sys.argv[1:]))
