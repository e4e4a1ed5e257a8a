"""``python -m march.sim2sim onnx=<student.onnx>``: the exported student in plain MuJoCo.

    python -m march.sim2sim onnx=outputs/<run>/student/student.onnx
    python -m march.sim2sim onnx=<bundle>/student.onnx course=stones difficulty=0.5 seed=3
    python -m march.sim2sim onnx=<bundle>/student.onnx control_delay_ms=15 depth_delay_steps=1
    python -m march.sim2sim onnx=<bundle>/student.onnx delays=train episodes=8
    python -m march.sim2sim onnx=<bundle>/student.onnx seconds=10 out=rollout.mp4

A sim-to-sim check of the deployment bundle that ``python -m march.export`` writes beside the
ONNX (``<stem>.deploy.json`` and one compiled scene per course, ``<stem>.<course>.mjb.gz``); the
loop itself is :mod:`march.sim2sim.runner`. Arguments (``key=value`` words, as every march tool;
parsed here without Hydra):

- ``onnx``: the exported student (required); its bundle must lie beside it.
- ``course``: ``hardware`` (start platform, 4 stones, goal) or ``stones`` (the evaluation grid).
- ``difficulty``: stones only - the grid level whose difficulty is nearest (0..1).
- ``seed``: stones: which course of that level (seed mod columns); both: the spawn pose noise
  (the evaluation's reset ranges; seed < 0 spawns exactly at the start point) and the delay
  draws. Episode k of ``episodes`` uses seed + k.
- ``seconds``: episode length [s] (ends earlier on a fall); ``episodes``: how many (default 1).
- ``vx``, ``vy``: the forward / lateral command [m/s] in the robot's body frame (default: the
  bundle's evaluation command); outside the trained ranges (``command_ranges``) or not finite
  (``vx=nan``) refused in one line.
- ``control_delay_ms``: the position target reaches the motors this late (rounded to the physics
  step, 5 ms); ``depth_delay_steps``: the depth image is this many control steps old;
  ``delays=train``: both drawn per episode as in training (``deploy.json`` ``latency``:
  U(0, 20) ms once per episode, the depth lag U{0, 1} every control step);
  ``delays=measured``: the control delay is the bundle's measured policy latency
  (``deploy.measured_latency_ms``, rounded up to the physics step), no depth lag. Default: none.
- ``report``: how many out-of-range lines per episode go to stderr (default 20).
- ``out``: optional video file (.mp4/.gif) from the scene's tracking camera; needs OpenGL
  offscreen (``MUJOCO_GL=egl``, the default here as in mjlab, or ``osmesa``) - refused with one
  line, before simulating, where there is none.
- ``threads``: onnxruntime intra-op threads (1, as on the robot).

Prints ONE JSON object: ``distance_m``, ``success``, ``fell``, ``abs_torque_nm``,
``abs_ang_jerk`` (march.evaluation.protocol's definitions, repeated in the bundle), ``steps``,
``ms_per_policy_call`` (median), ``ms_per_policy_call_p95``, ``ms_per_depth_image``,
``out_of_range`` (steps with an observation element outside training, counts per term), the
delays, the course cell and the arguments; with ``episodes`` > 1 the first episode's keys are
replaced by the means (``distance_m``, ``success_rate``) and ``episodes`` lists every one. Bad
input is one line on stderr and exit status 2, before simulating.

Why reading the bundle is safe: ``deploy.json`` is parsed with ``json`` (data only, no code);
the scene is MuJoCo's binary model format, read by MuJoCo's own loader, which checks the file's
header, version and every size before use (a file of another MuJoCo version is refused); the
ONNX file is a protobuf graph of tensor operators that onnxruntime executes (no Python, no
pickle). The JSON records the SHA-256 of the ONNX file and the scenes, checked before use.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import mujoco
import numpy as np

from march.sim2sim.deploy_bundle import Bundle, UsageError
from march.sim2sim.guard import CommandRefused, check_command

# The runner (onnxruntime) is imported after the bundle's checks: a bad file is refused
# without it (issue 59).
if TYPE_CHECKING:
    from march.sim2sim.runner import Delays

USAGE = (
    "usage: python -m march.sim2sim onnx=<student.onnx> [course=hardware|stones] "
    "[difficulty=0.5] [seed=0] [seconds=20] [episodes=1] [vx=..] [vy=..] "
    "[control_delay_ms=0] [depth_delay_steps=0] [delays=train|measured] [out=rollout.mp4] [threads=1]"
)


@dataclass
class Args:
    """The command line, typed."""

    onnx: str = ""
    course: str = "hardware"
    difficulty: float = 0.5
    seed: int = 0
    seconds: float = 20.0
    episodes: int = 1
    vx: float | None = None
    vy: float | None = None
    control_delay_ms: float | None = None
    depth_delay_steps: int = -1
    delays: str = "none"
    report: int = 20
    out: str = ""
    threads: int = 1


def parse_args(argv: Sequence[str]) -> Args:
    """``key=value`` words into :class:`Args` (Hydra-style, without Hydra)."""
    args = Args()
    types = {k: float if v is None else type(v) for k, v in vars(args).items()}
    for word in argv:
        key, eq, value = word.partition("=")
        if not eq:
            raise UsageError(f"expected key=value, got {word!r}. {USAGE}")
        key = key.lstrip("+")
        if key not in types:
            raise UsageError(f"unknown key {key!r}; keys: {', '.join(types)}. {USAGE}")
        try:
            typed = types[key](value)
        except ValueError:
            raise UsageError(f"{key}={value}: not a {types[key].__name__}") from None
        if isinstance(typed, float) and not math.isfinite(typed):
            raise UsageError(f"{key}={value}: must be a finite number")
        setattr(args, key, typed)
    if not args.onnx:
        raise UsageError(f"give onnx=<student.onnx> (written by python -m march.export). {USAGE}")
    if args.course not in ("hardware", "stones"):
        raise UsageError(f"course={args.course}: choose hardware or stones")
    if not 0.0 <= args.difficulty <= 1.0:
        raise UsageError(f"difficulty={args.difficulty}: must be in [0, 1]")
    if not args.seconds > 0.0:
        raise UsageError(f"seconds={args.seconds}: must be > 0")
    if args.episodes < 1:
        raise UsageError(f"episodes={args.episodes}: must be >= 1")
    if args.threads < 1:
        raise UsageError(f"threads={args.threads}: must be >= 1")
    if args.out and Path(args.out).suffix.lower() not in (".mp4", ".gif"):
        raise UsageError(f"out={args.out}: the video must end in .mp4 or .gif")
    if args.delays not in ("none", "train", "measured"):
        raise UsageError(
            f"delays={args.delays}: choose train (training's ranges), measured (the bundle's "
            "measured policy latency) or none"
        )
    explicit = args.control_delay_ms is not None or args.depth_delay_steps >= 0
    if args.delays != "none" and explicit:
        raise UsageError(
            f"delays={args.delays} sets the delays: drop control_delay_ms= / depth_delay_steps="
        )
    if args.control_delay_ms is not None and not 0.0 <= args.control_delay_ms <= 1000.0:
        raise UsageError(f"control_delay_ms={args.control_delay_ms}: must be in [0, 1000]")
    if args.depth_delay_steps < -1 or args.depth_delay_steps > 50:
        raise UsageError(f"depth_delay_steps={args.depth_delay_steps}: must be in [0, 50]")
    return args


class Video:
    """Offscreen frames from the scene's tracking camera (needs an OpenGL context)."""

    def __init__(self, model: mujoco.MjModel, path: str, fps: float) -> None:
        try:
            with warnings.catch_warnings():  # GLFW's own warnings say the same, twice
                warnings.simplefilter("ignore")
                self.renderer = mujoco.Renderer(model, 240, 320)  # sides divisible by 16
        except Exception as err:  # noqa: BLE001 - no GL backend: refuse in one line
            backend = os.environ.get("MUJOCO_GL", "default")
            raise UsageError(
                f"out={path}: no OpenGL context for offscreen video here with MUJOCO_GL={backend} "
                f"({type(err).__name__}); on Debian/Ubuntu install libegl1 libgl1-mesa-dri (EGL), "
                "or libosmesa6 and set MUJOCO_GL=osmesa; or drop out="
            ) from None
        cams = [model.camera(i).name for i in range(model.ncam)]
        self.camera = "robot/tracking" if "robot/tracking" in cams else -1
        self.path, self.fps, self.frames = path, fps, []

    def grab(self, data: mujoco.MjData) -> None:
        self.renderer.update_scene(data, camera=self.camera)
        self.frames.append(self.renderer.render().copy())

    def write(self) -> None:
        import imageio.v2 as imageio  # lazy: only for a video

        Path(self.path).parent.mkdir(parents=True, exist_ok=True)
        imageio.mimsave(self.path, self.frames, fps=self.fps)


def episode_delays(args: Args, spec: dict[str, Any], seed: int) -> Delays:
    """The delays of one episode from the arguments (fixed, or drawn as in training)."""
    from march.sim2sim.runner import Delays

    dt = float(spec["rates"]["physics_dt_s"])
    if args.delays == "train":
        return Delays.draw_train(spec["latency"], dt, seed)
    if args.delays == "measured":
        return Delays.measured(spec, seed)
    ms = 0.0 if args.control_delay_ms is None else args.control_delay_ms
    k = max(args.depth_delay_steps, 0)
    return Delays(int(round(ms / (dt * 1e3))), (k, k), np.random.default_rng(seed))


def _reporter(limit: int) -> Any:
    count = [0]

    def report(line: str) -> None:
        count[0] += 1
        if count[0] <= limit:
            print(f"[out-of-range] {line}", file=sys.stderr)
        elif count[0] == limit + 1:
            print("[out-of-range] ... (more in the JSON's out_of_range counts)", file=sys.stderr)

    return report


def run(args: Args) -> dict[str, Any]:
    """Load, check, simulate; the JSON row (also printed by :func:`main`)."""
    bundle = Bundle.load(args.onnx)
    spec = bundle.spec
    cmd = spec["command"]
    vx = cmd["lin_vel_x"] if args.vx is None else args.vx
    vy = cmd["lin_vel_y"] if args.vy is None else args.vy
    try:  # the yaw rate is the heading controller's, clipped into its trained range
        check_command(spec, (vx, vy, 0.0))
    except CommandRefused as err:
        raise UsageError(str(err)) from None
    from march.sim2sim.runner import Sim2Sim, rollout

    sim = Sim2Sim(bundle, args.course, args.threads)
    sim.set_command(vx, vy)
    cell = bundle.cell(args.course, args.difficulty, args.seed)
    video = Video(sim.model, args.out, 1.0 / sim.control_dt) if args.out else None
    rows = []
    t0 = time.perf_counter()
    for k in range(args.episodes):
        seed = args.seed + k if args.seed >= 0 else args.seed
        delays = episode_delays(args, spec, seed if seed >= 0 else 0)
        sim.reset(cell, seed, delays)
        row = rollout(
            sim, args.seconds, video.grab if video else None, report=_reporter(args.report)
        )
        rows.append({"seed": seed, **delays.describe(sim.physics_dt), **row})
    wall = time.perf_counter() - t0
    if video is not None:
        video.write()
    head = dict(rows[0])
    if args.episodes > 1:
        head.update(
            distance_m=float(np.mean([r["distance_m"] for r in rows])),
            success=all(r["success"] for r in rows),
            fell=any(r["fell"] for r in rows),
            steps=sum(r["steps"] for r in rows),
            seconds_simulated=sum(r["seconds_simulated"] for r in rows),
        )
    return {
        "course": args.course,
        "cell": [cell["row"], cell["col"]],
        "difficulty": cell["difficulty"],
        "goal_distance_m": cell["goal_distance"],
        "command": [vx, vy],
        "delays": args.delays
        if args.delays != "none"
        else {
            "control_delay_ms": head["control_delay_ms"],
            "depth_delay_steps": head["depth_delay_steps"][0],
        },
        **head,
        "success_rate": float(np.mean([r["success"] for r in rows])),
        "episodes": rows if args.episodes > 1 else None,
        "realtime_factor": head["seconds_simulated"] / wall if wall > 0 else None,
        "video": args.out or None,
        "onnx": str(args.onnx),
    }


def main(argv: Sequence[str] | None = None) -> None:
    try:
        args = parse_args(list(sys.argv[1:] if argv is None else argv))
        row = run(args)
    except UsageError as err:
        print(f"error: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    print(json.dumps(row))
