"""``python -m march.play``: roll one checkpoint out on the evaluation course and film it.

    python -m march.play student_ckpt=outputs/<run>/student/latest.pt            # rollout.mp4
    python -m march.play teacher_ckpt=outputs/<run>/teacher/latest.pt out=teacher.gif
    python -m march.play student_ckpt=... out=short.mp4 eval.episode_length_s=5 seed=3
    python -m march.play student_ckpt=... viewer=viser [port=8080] [steps=N]       # browser

``viewer=viser`` serves mjlab's browser viewer (viser) on ``port`` instead of writing a video:
play / pause / step / reset, march's reward terms in its Rewards tab, and the footstep plan drawn
(:mod:`march.env.plan_drawing`); it runs until Ctrl-C, or for ``steps`` control steps, and writes
no file (the env's build log goes to a temporary folder removed at the end). The video
(``viewer=video``, the default) gets the same plan drawing on its frames; the build log is written
beside it (``<out>.env.log``).

The checkpoint defines the policy: its saved config's reward set, student network and observation
layout replace the command line's (``march.store.provenance``); a conflicting explicit choice
(``reward=clf`` for a modelfree checkpoint) is one line on stderr. One env built for the ``eval``
purpose (the evaluation protocol as configured: command, episode length, depth corruption and
domain randomization), one episode (until time-out or a fall),
rendered offscreen on the CPU with MuJoCo by a camera that follows the robot's torso from a
three-quarter front view. Prints the course progress once per simulated second, then the file,
its frames and fps, and the rollout's distance and success as ``march.evaluation.protocol`` measures them.

Rendering needs an OpenGL backend for MuJoCo: mjlab picks ``MUJOCO_GL=egl`` (Mesa's software
EGL works without a GPU; Debian/Ubuntu packages ``libegl1 libgl1-mesa-dri``); set
``MUJOCO_GL=osmesa`` (package ``libosmesa6``) where EGL is missing.
"""

from __future__ import annotations

import sys
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from march.config import MarchConfig
from march.config.cli import fail, run_tool

# march.env (torch, mjlab) is imported in play(), after the checkpoint's file checks: a crafted
# file is refused without torch (issue 59: one line, under 200 MB resident).

USAGE = (
    "usage: python -m march.play student_ckpt=<file> | teacher_ckpt=<file> "
    "[out=rollout.mp4|.gif] [viewer=video|viser] [port=8080] [steps=N] [key=value ...]"
)
VIEWERS = ("video", "viser")
"""``viewer=``: an MP4 / GIF file (``video``) or mjlab's browser viewer (``viser``)."""
DEFAULT_OUT = "rollout.mp4"
SUFFIXES = (".mp4", ".gif")
TARGET_FPS = 25.0
"""Frames per second of simulated time the video aims at (every k-th control step is drawn)."""
"""Tracking camera on the torso: in front of the robot and to its right, looking back at it."""

Policy = Callable[[dict[str, Any]], Any]


@dataclass
class ViewerArgs:
    """play's own arguments (not config keys): ``viewer=``, ``port=``, ``steps=``."""

    viewer: str = "video"
    port: int = 8080
    steps: int | None = None


def viewer_args(args: list[str]) -> tuple[ViewerArgs, list[str]]:
    """Take ``viewer=``, ``port=`` and ``steps=`` out of ``args``; one line on a bad value."""
    out, rest = ViewerArgs(), []
    for arg in args:
        key, _, value = arg.partition("=")
        if key == "viewer":
            if value not in VIEWERS:
                fail(f"viewer={value}: choose one of {', '.join(VIEWERS)}")
            out.viewer = value
        elif key in ("port", "steps"):
            if not value.isdigit() or not (0 < int(value) < (65536 if key == "port" else 10**9)):
                fail(f"{arg}: give a positive integer{' below 65536' if key == 'port' else ''}")
            setattr(out, key, int(value))
        else:
            rest.append(arg)
    return out, rest


@dataclass
class PlayResult:
    out: Path
    kind: str
    frames: int
    fps: float
    steps: int
    duration_s: float
    distance_m: float
    success: bool
    fell: bool


def checkpoint_arg(cfg: MarchConfig) -> tuple[str, str]:
    """(kind, path) of the one checkpoint given, or a clear error."""
    given = [(k, p) for k, p in (("student", cfg.student_ckpt), ("teacher", cfg.teacher_ckpt)) if p]
    if not given:
        fail(
            "give a checkpoint: student_ckpt=<file> (outputs/<run>/student/latest.pt) or "
            f"teacher_ckpt=<file>. {USAGE}"
        )
    if len(given) > 1:
        fail("give student_ckpt=<file> or teacher_ckpt=<file>, not both")
    kind, path = given[0]
    if not Path(path).is_file():
        fail(f"{kind}_ckpt={path}: no such file")
    return kind, path


def out_path(cfg: MarchConfig) -> Path:
    out = Path(cfg.out or DEFAULT_OUT)
    if out.suffix.lower() not in SUFFIXES:
        fail(f"out={out}: write a video ending in {' or '.join(SUFFIXES)}")
    return out


def frame_stride(step_dt: float) -> int:
    """Draw every k-th control step so the video runs near TARGET_FPS in real time."""
    return max(1, round(1.0 / (TARGET_FPS * step_dt)))


def write_video(path: Path, frames: Sequence[Any], fps: float) -> None:
    import imageio_ffmpeg
    import mediapy

    mediapy.set_ffmpeg(imageio_ffmpeg.get_ffmpeg_exe())
    path.parent.mkdir(parents=True, exist_ok=True)
    codec = "gif" if path.suffix.lower() == ".gif" else "h264"
    mediapy.write_video(path, frames, fps=fps, codec=codec)


def play(
    cfg: MarchConfig,
    env: Any = None,
    explicit_overrides: Sequence[str] = (),
    view: ViewerArgs | None = None,
) -> PlayResult | int:
    """Roll the checkpoint out for one episode on the eval env and write the video.

    ``env`` (an ``eval``-purpose env) may be passed in to reuse one; otherwise one env is built
    and closed here. ``explicit_overrides``: the command line's ``key=value`` arguments, which
    must not contradict the checkpoint's policy.
    """
    import torch

    from march.config import ConfigError
    from march.env.plan_drawing import enable_plan_drawing
    from march.env.rendering import HEIGHT, WIDTH, make_renderer, rendering_error
    from march.store.checkpoint import CheckpointError
    from march.store.gate import policy_from_checkpoint as read_policy

    view = view or ViewerArgs()
    kind, path = checkpoint_arg(cfg)
    out = out_path(cfg) if view.viewer == "video" else Path(DEFAULT_OUT)
    try:  # a wrong or unreadable file fails here (the disk gate), before the env is built
        payload, policy_cfg, changes = read_policy(
            cfg, kind, path, explicit_overrides, device=cfg.compute.device
        )
    except (CheckpointError, ConfigError) as err:
        fail(str(err))
    if changes and env is not None:
        fail(
            f"the env passed to play() was built for another policy than {kind}_ckpt={path} "
            f"({changes[0].split('policy: ', 1)[-1]}); build it from the checkpoint's config"
        )
    cfg = policy_cfg
    for change in changes:
        print(change, flush=True)
    why = rendering_error() if view.viewer == "video" else None
    if why:
        fail(why)
    from march.env.course import CourseRuler
    from march.evaluation.protocol import policy_from_checkpoint

    torch.manual_seed(cfg.seed)
    own_env = env is None
    log_dir = None
    if own_env:
        from march.env.build import make_env

        if view.viewer == "video":
            log = Path(out).with_suffix(".env.log")  # beside the video asked for
        else:  # the browser viewer writes no file: its build log lives while play runs
            log_dir = tempfile.TemporaryDirectory(prefix="march-play-")
            log = Path(log_dir.name) / "env.log"
        env = make_env(cfg, "eval", num_envs=1, log=log)
    renderer = None
    try:
        obs, _ = env.reset()
        try:
            policy = policy_from_checkpoint(env, cfg, kind, payload, path)
        except CheckpointError as err:
            fail(str(err))
        if view.viewer == "viser":
            return serve(env, policy, kind, path, view)
        term = enable_plan_drawing(env)
        renderer = make_renderer(env)
        ruler = CourseRuler(env)
        dt = env.step_dt
        stride = frame_stride(dt)
        fps = 1.0 / (stride * dt)
        per_second = max(1, round(1.0 / dt))
        horizon = int(env.max_episode_length)
        print(
            f"[play] {kind} {path}: one episode of up to {horizon * dt:g} s on the eval course "
            f"(command vx {cfg.eval.command_vx:g} m/s), {WIDTH}x{HEIGHT} at {fps:g} fps",
            flush=True,
        )

        def draw() -> Any:
            renderer.update(env.sim.data, debug_vis_callback=term.debug_vis)
            return renderer.render().copy()

        frames = [draw()]
        distance, fell, steps = 0.0, False, 0
        with torch.no_grad():
            for step in range(1, horizon + 2):
                before = float(ruler.progress()[0])
                obs, _, terminated, truncated, _ = env.step(policy(obs))
                steps = step
                if bool(terminated[0] | truncated[0]):
                    # The env has already reset: the episode's last state is the one before.
                    distance, fell = before, bool(terminated[0])
                    break
                distance = float(ruler.progress()[0])
                if step % stride == 0:
                    frames.append(draw())
                if step % per_second == 0:
                    print(f"  t {step * dt:5.1f} s  distance {distance:6.2f} m", flush=True)
        success = bool(ruler.reached_goal(torch.tensor([distance], device=env.device))[0])
        success = success and not fell
        write_video(out, frames, fps)
    finally:
        if renderer is not None:
            renderer.close()
        if own_env:
            env.close()
        if log_dir is not None:
            log_dir.cleanup()
    result = PlayResult(
        out=out,
        kind=kind,
        frames=len(frames),
        fps=fps,
        steps=steps,
        duration_s=steps * dt,
        distance_m=distance,
        success=success,
        fell=fell,
    )
    end = "fell" if fell else "time-out"
    print(
        f"wrote {out}: {result.frames} frames at {fps:g} fps ({result.frames / fps:.1f} s); "
        f"episode {result.duration_s:.2f} s ({end}), distance {distance:.2f} m, "
        f"success {'yes' if success else 'no'}",
        flush=True,
    )
    return result


def serve(env: Any, policy: Policy, kind: str, path: str, view: ViewerArgs) -> int:
    """mjlab's browser viewer on ``env`` and ``policy`` (``viewer=viser``): the control steps run."""
    from march.env.browser_viewer import open_viewer

    def ready(url: str) -> None:
        print(
            f"[play] {kind} {path}: mjlab's viewer at {url} (Rewards tab: march's reward terms; "
            "the plan is drawn)" + (f"; {view.steps} steps" if view.steps else "; Ctrl-C stops"),
            flush=True,
        )

    steps = open_viewer(env, policy, port=view.port, steps=view.steps, on_ready=ready)
    print(f"[play] viewer closed after {steps} control steps", flush=True)
    return steps


def expected_frames(steps: int, stride: int) -> int:
    """Frames ``play`` writes for an episode of ``steps`` control steps (the reset state is 1)."""
    return 1 + (steps - 1) // stride  # the last step's state belongs to the auto-reset episode


def main(argv: Sequence[str] | None = None) -> None:
    view, args = viewer_args(list(sys.argv[1:] if argv is None else argv))
    from march.store.checkpoint_file import check_checkpoint_files

    # The checkpoint judged (link, size, zip records) before the term check loads the simulator.
    job = lambda cfg: play(cfg, explicit_overrides=args, view=view)  # noqa: E731
    run_tool(job, args, usage=USAGE, before_terms=check_checkpoint_files)


if __name__ == "__main__":
    main(sys.argv[1:])
