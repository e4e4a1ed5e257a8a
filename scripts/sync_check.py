"""Where a training step still waits for the GPU: one teacher iteration, one distillation
rollout and the bare env steps of march and of mjlab's rough task under
``torch.cuda.set_sync_debug_mode("warn")``, every synchronising call's source line written to a
file (the ``syncs`` phase of ``scripts/gpu_check.py``).

    python scripts/sync_check.py OUT_FILE [--parts=env_march,env_rough] [overrides ...]

Parts, each recorded as a phase of the file, in this order unless ``--parts=a,b`` picks
others: ``env_march`` and ``env_rough``: ``teacher.num_steps_per_env`` steps of the march
teacher env and of bare mjlab rough alone (random actions drawn beforehand, under
``inference_mode``), so that the file says whether march's step issues more syncs than bare
mjlab's (first: the GPU check's figure); then ``teacher`` (a teacher iteration's rollout and
bookkeeping, the update left out) and ``distill`` (a distillation rollout). Each part prints
its count (``[syncs] part: N syncs in S env steps``) the moment it ends.

One line per sync (tab-separated): the phase, the env step of the part it follows (1 from the
first step's start to the second's, 0 before the first), the innermost frame outside torch
(``file:line``), the innermost frame in march's own code (or ``-``: for a sync inside mjlab
called from a march runner, that is the runner's line), and CUDA's message; then a count per
source line at the end of the file. A ``# recorded:`` line names the phases in the file and a
``# steps:`` line the env steps of each: the file is rewritten after each part, so a run
stopped by a time limit keeps what it recorded. On a machine without CUDA the steps run the same and the file says that
nothing could be recorded (the tests run it so).
"""

from __future__ import annotations

import sys
import tempfile
import traceback
import warnings
from collections import Counter
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # run as a script: import this checkout's march


def _frames() -> tuple[str, str]:
    """(innermost frame outside torch, innermost frame in march/) of the current stack."""
    outside, march = "-", "-"
    for fr in reversed(traceback.extract_stack()[:-3]):
        name = fr.filename
        if "/torch/" in name or "warnings.py" in name or name == __file__:
            continue
        if outside == "-":
            outside = f"{_short(name)}:{fr.lineno}"
        if "/march/" in name and march == "-":
            march = f"{_short(name)}:{fr.lineno}"
            break
    return outside, march


def _short(name: str) -> str:
    if name.startswith(str(ROOT)):
        return name[len(str(ROOT)) + 1 :]
    return name.partition("site-packages/")[2] or name


def _counting_steps(env: Any, phase: dict[str, Any]) -> Any:
    """``env`` whose ``step`` first advances ``phase["step"]``: each sync is recorded with the
    env step it follows (0 before the first), so that a line that syncs in several steps of a
    part is told from a read once per iteration."""
    step = env.step

    def counted(*args: Any, **kwargs: Any) -> Any:
        phase["step"] += 1
        return step(*args, **kwargs)

    env.step = counted
    return env


def _write(out: Path, hits: list[tuple[str, ...]], cuda: bool, steps: dict[str, int]) -> None:
    """The syncs file (module docstring), replaced in one rename; ``steps``: the phases recorded
    so far and the env steps of each (the ``# recorded:`` and ``# steps:`` lines)."""
    tmp = out.with_name(out.name + ".tmp")
    with tmp.open("w") as f:
        if not cuda:
            f.write("# no CUDA device: torch.cuda.set_sync_debug_mode recorded nothing\n")
        f.write(f"# recorded: {', '.join(steps)}\n")
        f.write(f"# steps: {', '.join(f'{k} {v}' for k, v in steps.items())}\n")
        f.write("phase\tstep\tsource\tmarch\tmessage\n")
        for h in hits:
            f.write("\t".join(h) + "\n")
        f.write("# count\tphase\tsource\tmarch\n")
        for (ph, src, march), n in Counter((h[0], h[2], h[3]) for h in hits).most_common():
            f.write(f"# {n}\t{ph}\t{src}\t{march}\n")
    tmp.replace(out)


def _record_env_steps(
    make: Any, steps: int, seed: int, cuda: bool, phase: dict[str, Any], name: str
) -> int:
    """Step the env ``make()`` builds ``steps`` times with random actions (drawn before the
    recording) under ``inference_mode``, as the rollouts do, recording its syncs as phase
    ``name`` (after a reset and 5 warm-up steps); returns the steps recorded."""
    import torch

    from march.bench.harness import Actions

    env = _counting_steps(make(), phase)
    try:
        draw = Actions(env, "random", seed)
        with torch.inference_mode():
            env.reset()
            for _ in range(5):
                env.step(draw())
            actions = [draw() for _ in range(steps)]
            if cuda:
                torch.cuda.synchronize()
                torch.cuda.set_sync_debug_mode("warn")
            phase["name"], phase["step"] = name, 0
            try:
                for a in actions:
                    env.step(a)
            finally:
                if cuda:
                    torch.cuda.set_sync_debug_mode(0)
    finally:
        env.close()
    return phase["step"]


PARTS = ("env_march", "env_rough", "teacher", "distill")
"""The parts in the order they run by default: march's env and bare rough's first (the figure
the GPU check needs most: syncs per step, march vs rough), then the runners' rollouts."""


def parse_parts(argv: list[str]) -> tuple[list[str], list[str]]:
    """``--parts=a,b`` taken off ``argv`` (default :data:`PARTS`): (parts, the rest)."""
    parts, rest = list(PARTS), []
    for arg in argv:
        if arg.startswith("--parts="):
            parts = [p for p in arg.split("=", 1)[1].split(",") if p]
            bad = [p for p in parts if p not in PARTS]
            if bad or not parts:
                raise SystemExit(f"sync_check: --parts: expected names from {', '.join(PARTS)}")
        else:
            rest.append(arg)
    return parts, rest


def main(argv: list[str]) -> int:
    import torch

    from march.bench.env_speed import ROUGH_TASK
    from march.config.cli import load
    from march.env.build import bare_env, make_env
    from march.learn.distill import DistillRunner
    from march.learn.metrics import MetricsLog
    from march.learn.teacher import EpisodeStats, TeacherRunner

    parts, argv = parse_parts(argv)
    out = Path(argv[0])
    cfg = load(["logger=csv", *argv[1:]])
    cuda = cfg.compute.device.startswith("cuda") and torch.cuda.is_available()
    hits: list[tuple[str, ...]] = []
    phase: dict[str, Any] = {"name": "", "step": 0}
    steps: dict[str, int] = {}
    shared: dict[str, Any] = {}

    def record(message, category, filename, lineno, file=None, line=None):
        text = str(message)
        if "synchroniz" not in text:
            return
        outside, march = _frames()
        step = str(phase["step"])
        hits.append((phase["name"], step, outside, march, text.splitlines()[0][:120]))

    run = Path(tempfile.mkdtemp(prefix="sync_check_"))

    def teacher_part() -> int:
        env = _counting_steps(make_env(cfg, "teacher"), phase)
        log = MetricsLog(run, cfg.logger, "t")
        try:
            teacher = TeacherRunner(env, cfg, run, log)
            teacher.learn(1)  # warm-up: first-use set-ups, lazy buffers
            real_update = teacher.alg.update

            def update():  # the update may read values: only the rollout is recorded
                if cuda:
                    torch.cuda.set_sync_debug_mode(0)
                return real_update()

            teacher.alg.update = update
            phase["name"], phase["step"] = "teacher", 0
            if cuda:
                torch.cuda.set_sync_debug_mode("warn")
            teacher.learn(2)
            shared["payload"] = teacher.payload()
        finally:
            if cuda:
                torch.cuda.set_sync_debug_mode(0)
            log.close()
            env.close()
        return phase["step"]

    def distill_part() -> int:
        if "payload" not in shared:  # the teacher part did not run: a fresh teacher's weights
            env = make_env(cfg, "teacher")
            log = MetricsLog(run, cfg.logger, "t")
            try:
                shared["payload"] = TeacherRunner(env, cfg, run, log).payload()
            finally:
                log.close()
                env.close()
        env = _counting_steps(make_env(cfg, "student"), phase)
        log = MetricsLog(run / "s", cfg.logger, "s")
        try:
            student = DistillRunner(env, cfg, run / "s", log, shared["payload"], "teacher.pt")
            stats = EpisodeStats(env.num_envs, cfg.compute.device)
            student._rollout(stats)  # warm-up
            phase["name"], phase["step"] = "distill", 0
            if cuda:
                torch.cuda.synchronize()
                torch.cuda.set_sync_debug_mode("warn")
            student._rollout(stats)
        finally:
            if cuda:
                torch.cuda.set_sync_debug_mode(0)
            log.close()
            env.close()
        return phase["step"]

    n, seed, device = cfg.compute.num_envs, cfg.seed, cfg.compute.device
    n_steps = cfg.teacher.num_steps_per_env
    run_part = {
        "env_march": lambda: _record_env_steps(
            lambda: make_env(cfg, "teacher"), n_steps, seed, cuda, phase, "env_march"
        ),
        "env_rough": lambda: _record_env_steps(
            lambda: bare_env(ROUGH_TASK, n, seed, device), n_steps, seed, cuda, phase, "env_rough"
        ),
        "teacher": teacher_part,
        "distill": distill_part,
    }
    old = warnings.showwarning
    warnings.showwarning = record
    warnings.simplefilter("always")
    try:
        for part in parts:
            steps[part] = run_part[part]()
            _write(out, hits, cuda, steps)  # kept if a time limit stops the later parts
            n_part = sum(1 for h in hits if h[0] == part)
            print(
                f"[syncs] {part}: {n_part} syncs in {steps[part]} env steps "
                f"({n_part / max(steps[part], 1):.2f} per step)"
                + ("" if cuda else ": no CUDA, nothing recorded"),
                file=sys.stderr,
                flush=True,
            )
    finally:
        warnings.showwarning = old
    n_march = sum(1 for h in hits if h[3] != "-")
    print(f"[syncs] {len(hits)} syncs recorded ({n_march} with march code on the stack) -> {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
