"""march.play: argument errors (fast) and a short filmed rollout of a student (sim)."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import asdict
from pathlib import Path

import pytest
import torch

from march import play
from march.env import rendering

REPO = Path(__file__).resolve().parent.parent


def test_no_checkpoint_exits_2_with_one_line():
    proc = subprocess.run(
        [sys.executable, "-m", "march.play", "out=x.mp4"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    assert proc.stderr.startswith("error: give a checkpoint: student_ckpt=<file>")
    assert len([ln for ln in [*proc.stdout.splitlines(), *proc.stderr.splitlines()] if ln]) == 1
    assert "Traceback" not in proc.stderr


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["student_ckpt=nope.pt"], "student_ckpt=nope.pt: no such file"),
        (["teacher_ckpt=nope.pt"], "teacher_ckpt=nope.pt: no such file"),
        (["student_ckpt=a.pt", "teacher_ckpt=b.pt"], "not both"),
        (["student_ckpt={ckpt}", "out=video.avi"], "out=video.avi: write a video ending in"),
        (["student_ckpt={ckpt}"], "this is a 'teacher' checkpoint, not a student"),
        (["teacher_ckpt={junk}"], "not a readable checkpoint"),
    ],
)
def test_argument_errors(args, message, tmp_path, capsys):
    ckpt, junk = tmp_path / "teacher.pt", tmp_path / "junk.pt"
    torch.save({"kind": "teacher"}, ckpt)
    junk.write_bytes(b"not a checkpoint")
    with pytest.raises(SystemExit) as exc:
        play.main([a.format(ckpt=ckpt, junk=junk) for a in args])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and message in err


@pytest.mark.sim
def test_play_writes_a_moving_video_of_a_student(tmp_path):
    why = rendering.rendering_error()  # first: without a GL library even ``import mujoco`` fails
    if why:
        pytest.skip(f"offscreen rendering unavailable: {why}")
    import imageio.v3 as iio

    from march.config.cli import load
    from march.env.build import make_env
    from march.learn.distill import build_student, student_layout

    torch.set_num_threads(1)
    ckpt, out = tmp_path / "student.pt", tmp_path / "rollout.gif"
    # 0.3 s: 15 steps, 8 frames (one every other step): a moving video, its frame count and rate
    cfg = load(["compute=smoke", "eval.episode_length_s=0.3", f"student_ckpt={ckpt}", f"out={out}"])
    env = make_env(cfg, "eval", num_envs=1)
    try:
        # A freshly initialised student stands in for a trained one (same layout, same loader).
        obs, _ = env.reset()
        layout = student_layout(obs, cfg, env.action_manager.total_action_dim)
        student = build_student(cfg, layout, cfg.compute.device)
        payload = {
            "kind": "student",
            "iteration": 0,
            "env_steps": 0,
            "config": asdict(cfg),
            "layout": layout,
            "student_state_dict": student.state_dict(),
        }
        torch.save(payload, ckpt)
        result = play.play(cfg, env=env)
        horizon = int(env.max_episode_length)
        stride = play.frame_stride(env.step_dt)
    finally:
        env.close()

    assert result.out == out and out.is_file()
    assert result.fps == pytest.approx(1.0 / (stride * cfg.env.sim_dt * cfg.env.decimation))
    if not result.fell:
        assert result.steps == horizon
    assert result.frames == play.expected_frames(result.steps, stride)
    frames = iio.imread(out, index=None)
    assert frames.shape[0] == result.frames
    assert frames.shape[1:3] == (rendering.HEIGHT, rendering.WIDTH)
    assert any(not (frames[i] == frames[0]).all() for i in range(1, len(frames)))
    assert result.distance_m >= 0.0


@pytest.mark.sim
def test_the_browser_viewer_writes_nothing_into_the_working_directory(
    tmp_path, monkeypatch, capsys
):
    """``python -m march.play ... viewer=viser`` asks for no file: play's path up to the viewer
    (checkpoint, its own env built with its build log, the policy) run from an empty working
    directory leaves it empty (it left ``rollout.env.log`` there); the build log lives in a
    temporary folder while the viewer runs, and is gone after. mjlab's viewer itself is stood in
    for (serving it is the slow test below)."""
    from march.config.cli import load
    from march.env.build import make_env
    from march.learn.distill import build_student, student_layout

    torch.set_num_threads(1)
    ckpt, cwd = tmp_path / "ckpt" / "student.pt", tmp_path / "cwd"
    ckpt.parent.mkdir()
    cwd.mkdir()
    cfg = load(["compute=smoke", f"student_ckpt={ckpt}"])
    env = make_env(cfg, "eval", num_envs=1)
    try:  # a freshly initialised student stands in for a trained one (same layout and loader)
        obs, _ = env.reset()
        layout = student_layout(obs, cfg, env.action_manager.total_action_dim)
        student = build_student(cfg, layout, cfg.compute.device)
    finally:
        env.close()
    payload = {"kind": "student", "iteration": 0, "env_steps": 0, "config": asdict(cfg)}
    torch.save(payload | {"layout": layout, "student_state_dict": student.state_dict()}, ckpt)
    capsys.readouterr()
    logs = []

    def serve(env, policy, kind, path, view):  # what the viewer finds: the env's build log
        printed = capsys.readouterr().out
        logs.append(Path(printed.split("(build log: ")[1].split(")")[0]))
        assert logs[0].stat().st_size > 0, printed
        return 7

    monkeypatch.setattr(play, "serve", serve)
    monkeypatch.chdir(cwd)
    assert play.play(cfg, view=play.ViewerArgs(viewer="viser", steps=7)) == 7
    assert list(cwd.iterdir()) == [] and list(ckpt.parent.iterdir()) == [ckpt]
    (log,) = logs
    assert cwd not in log.parents and not log.exists() and not log.parent.exists()


def test_checkpoint_policy_conflict_is_one_line_before_any_env(tmp_path, capsys):
    """A modelfree student checkpoint played with reward=clf: one line naming both values."""
    from march.config.cli import load

    ckpt = tmp_path / "student.pt"
    saved = asdict(load(["reward=modelfree"]))
    torch.save({"kind": "student", "iteration": 0, "env_steps": 0, "config": saved}, ckpt)
    with pytest.raises(SystemExit) as exc:
        play.main([f"student_ckpt={ckpt}", "reward=clf", f"out={tmp_path / 'x.mp4'}"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert err.startswith(f"error: reward=clf conflicts with student_ckpt={ckpt}")
    assert "reward.name=modelfree" in err
    assert not (tmp_path / "x.env.log").exists()  # no env was built


# --------------------------------------------------------------- the plan drawn (issue 40)


def test_considered_stones_are_the_m_nearest_each_foothold():
    """Hand-made stones on a line at x = 0..9; footholds at x = 2.1 and 7.9, m = 2: the two
    nearest 2.1 are stones 2 (0.1 away) and 3 (0.9; stone 1 is 1.1); nearest 7.9 are 8 (invalid,
    skipped), 7 (0.9) and 9 (1.1) -> {2, 3, 7, 9}."""
    from march.env.plan_drawing import considered_stones

    centers = torch.zeros(10, 3)
    centers[:, 0] = torch.arange(10.0)
    valid = torch.ones(10, dtype=torch.bool)
    valid[8] = False
    feet = torch.tensor([[2.1, 0.0, 0.0], [7.9, 0.0, 0.0]])
    got = considered_stones(centers, valid, feet, 2)
    assert torch.nonzero(got)[:, 0].tolist() == [2, 3, 7, 9]
    assert not considered_stones(centers, torch.zeros(10, dtype=torch.bool), feet, 2).any()


class _Recorder:
    """An mjlab DebugVisualizer that records what is drawn (a real subclass: the same calls a
    viewer receives), with a label per drawn item."""

    def __init__(self):
        from mjlab.viewer.debug_visualizer import DebugVisualizer

        class Rec(DebugVisualizer):
            env_idx, show_all_envs, meansize = 0, False, 0.1

            def __init__(self):
                self.items = []

            def _add(self, kind, *args, label=None, **kw):
                self.items.append((kind, args, label))

            def add_arrow(self, *a, **k):
                self._add("arrow", *a, **k)

            def add_ghost_mesh(self, *a, **k):
                self._add("ghost", *a, **k)

            def add_frame(self, *a, **k):
                self._add("frame", *a, **k)

            def add_sphere(self, *a, **k):
                self._add("sphere", *a, **k)

            def add_cylinder(self, *a, **k):
                self._add("cylinder", *a, **k)

            def add_ellipsoid(self, *a, **k):
                self._add("ellipsoid", *a, **k)

            def add_box(self, *a, **k):
                self._add("box", *a, **k)

            def clear(self):
                self.items.clear()

        self.vis = Rec()


@pytest.mark.sim
def test_plan_drawn_through_the_debug_visualizer_matches_the_term():
    """On the real eval env: every planned foothold is drawn where the term planned it,
    numbered 1..N, alternating feet with step 1 on the swing foot; the swing target post stands
    on step.target; the considered stones include the stone under each foothold."""
    import numpy as np

    from march.config.cli import load
    from march.env.build import make_env
    from march.env.plan_drawing import FOOT_RADIUS, enable_plan_drawing

    torch.set_num_threads(1)
    cfg = load(["compute=smoke"])
    env = make_env(cfg, "eval", num_envs=1)
    try:
        env.reset()
        zero = torch.zeros(1, env.action_manager.total_action_dim)
        for _ in range(3):
            env.step(zero)
        term = enable_plan_drawing(env)
        rec = _Recorder().vis
        env.update_visualizers(rec)  # mjlab's path: managers -> command term -> march's drawing
        video_labels = None
        if rendering.rendering_error() is None:  # the video's frames: the same drawing
            renderer = rendering.make_renderer(env)
            try:
                renderer.update(env.sim.data)
                bare = renderer.renderer.scene.ngeom
                renderer.update(env.sim.data, debug_vis_callback=term.debug_vis)
                scene = renderer.renderer.scene
                assert scene.ngeom - bare == len(rec.items)
                video_labels = [scene.geoms[i].label for i in range(bare, scene.ngeom)]
            finally:
                renderer.close()
        plan = term.plan_footholds[0].numpy()
        swing_is_left = not bool(term.stance_is_left[0])
        target = term.step.target[0].numpy()
        n_stones = int(term.footholds.valid[0].sum())
    finally:
        env.close()
    balls = [(a, lab) for kind, a, lab in rec.items if kind == "sphere" and lab != "CoM reference"]
    assert len(balls) == plan.shape[0]
    for j, (args, label) in enumerate(balls):
        left = (j % 2 == 0) == swing_is_left
        assert label == f"{j + 1}{'L' if left else 'R'}"
        assert np.allclose(args[0], plan[j] + np.array([0, 0, FOOT_RADIUS * 0.6]), atol=1e-6)
    posts = [a for kind, a, _ in rec.items if kind == "cylinder" and a[2] == 0.012]
    assert len(posts) == 1 and np.allclose(posts[0][0], target, atol=1e-6)
    boxes = [a for kind, a, _ in rec.items if kind == "box"]
    assert 0 < len(boxes) <= n_stones
    for p in plan:  # the stone under each planned foothold is drawn as considered
        assert any(
            abs(b[0][0] - p[0]) <= b[1][0] + 1e-4 and abs(b[0][1] - p[1]) <= b[1][1] + 1e-4
            for b in boxes
        )
    assert [lab for kind, _, lab in rec.items if lab == "CoM reference"] == ["CoM reference"]
    if video_labels is not None:  # the numbers are written on the video's foothold balls
        assert [x for x in video_labels if x] == [lab for _, lab in balls]


def test_viser_labels_ride_the_scene_frame_over_their_balls():
    """In viser each foothold label is a child of mjviser's ``/fixed_bodies`` frame at its ball's
    world position + 6 cm (the frame carries the scene offset, in the same update as the balls);
    without that frame (an older scene) the offset read now is added."""
    import types

    import numpy as np

    from march.env.plan_drawing import FOOT_RADIUS, draw_picture

    feet = np.array([[1.0, 0.2, 0.1], [1.3, -0.1, 0.15], [1.6, 0.2, 0.05]])
    pic = {
        "stone_center": np.zeros((0, 3)),
        "stone_half": np.zeros((0, 3)),
        "com_path": np.array([[0.0, 0.0, 0.7], [0.2, 0.0, 0.7]]),
        "com_now": np.array([0.1, 0.0, 0.7]),
        "target": feet[0],
        "swing_foot": np.array([0.5, 0.2, 0.1]),
        "footholds": feet,
        "lands_left": np.array([True, False, True]),
    }
    offset = np.array([-4.0, 2.5, -0.3])  # the camera tracks the robot: the scene is shifted
    for frame in (types.SimpleNamespace(name="/fixed_bodies"), None):
        labels, balls = [], []

        def add_label(name, text, position, _out=labels, **_):
            _out.append((name, text, np.array(position)))

        def add_sphere(center, *a, label=None, _out=balls, **k):
            _out.append((label, center))

        scene = types.SimpleNamespace(add_label=add_label)
        vis = types.SimpleNamespace(
            server=types.SimpleNamespace(scene=scene),
            fixed_bodies_frame=frame,
            _scene_offset=offset,
            add_box=lambda *a, **k: None,
            add_cylinder=lambda *a, **k: None,
            add_arrow=lambda *a, **k: None,
            add_sphere=add_sphere,
        )
        draw_picture(pic, vis)
        feet_balls = [(lab, c) for lab, c in balls if lab != "CoM reference"]
        assert [t for _, t, _ in labels] == [lab for lab, _ in feet_balls] == ["1L", "2R", "3L"]
        for j, ((name, _, at), (_, ball)) in enumerate(zip(labels, feet_balls, strict=True)):
            assert np.allclose(ball, feet[j] + [0, 0, 0.6 * FOOT_RADIUS])
            if frame is not None:
                assert name == f"/fixed_bodies/march_plan/foothold_{j}"
                assert np.allclose(at, ball + [0, 0, 0.06])
            else:
                assert name == f"/march_plan/foothold_{j}"
                assert np.allclose(at, ball + [0, 0, 0.06] + offset)


@pytest.mark.skipif(sys.platform != "linux", reason="mjlab picks EGL on Linux only")
def test_a_march_env_module_imported_first_leaves_mujoco_on_egl():
    """mujoco reads ``MUJOCO_GL`` once, when it loads, and mjlab sets it to ``egl`` on import: a
    ``march.env`` module that imports mujoco imports mjlab before it, or a process whose first
    import is that module gets GLFW's context and, without a display, aborts when it renders
    (it did: the colour test's import of ``stone_terrain`` killed this file's video test)."""
    import ast
    import os

    env_dir = REPO / "march" / "env"
    first = [
        p.stem
        for p in sorted(env_dir.glob("*.py"))
        if any(
            isinstance(node, ast.Import) and any(a.name == "mujoco" for a in node.names)
            for node in ast.parse(p.read_text()).body
        )
    ]
    assert {"stone_terrain", "g1"} <= set(first)
    clean = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    for module in first:
        out = subprocess.run(
            [sys.executable, "-c", FIRST_MUJOCO_GL, f"march.env.{module}"],
            cwd=REPO, env=clean, capture_output=True, text=True, timeout=300,
        )  # fmt: skip
        assert out.returncode == 0, out.stderr[-2000:]
        assert out.stdout.split()[-1] == "mujoco.egl", (module, out.stdout)


FIRST_MUJOCO_GL = """
import importlib, importlib.abc, importlib.util, os, sys
class Watch(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name != "mujoco":
            return None
        sys.meta_path.remove(self)
        spec = importlib.util.find_spec("mujoco")
        run = spec.loader.exec_module
        def exec_module(module):
            run(module)
            print(module.GLContext.__module__, flush=True)
            os._exit(0)
        spec.loader.exec_module = exec_module
        return spec
sys.meta_path.insert(0, Watch())
importlib.import_module(sys.argv[1])
print("mujoco never imported", flush=True)
"""
"""``python -c FIRST_MUJOCO_GL <module>``: import ``module`` and print the GL context mujoco chose
when it was first loaded, then stop there (mujoco fixes its context at that moment: the rest of
the import, mujoco_warp's and mjlab's ~6 s of CPU, cannot change it)."""


def test_viewer_argument_errors_are_one_line(capsys):
    for args, message in (
        (["viewer=vr"], "viewer=vr: choose one of video, viser"),
        (["viewer=viser", "port=0"], "port=0: give a positive integer below 65536"),
        (["viewer=viser", "steps=x"], "steps=x: give a positive integer"),
    ):
        with pytest.raises(SystemExit) as exc:
            play.main(args)
        assert exc.value.code == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ") and message in err and len(err.splitlines()) == 1


def _smoke_student(path: Path) -> None:
    """A freshly initialised smoke-scale student checkpoint (the trained one's layout)."""
    from march.config.cli import load
    from march.env.build import make_env
    from march.learn.distill import build_student, student_layout

    cfg = load(["compute=smoke"])
    env = make_env(cfg, "eval", num_envs=1)
    try:
        obs, _ = env.reset()
        layout = student_layout(obs, cfg, env.action_manager.total_action_dim)
        student = build_student(cfg, layout, cfg.compute.device)
    finally:
        env.close()
    torch.save(
        {
            "kind": "student",
            "iteration": 0,
            "env_steps": 0,
            "config": asdict(cfg),
            "layout": layout,
            "student_state_dict": student.state_dict(),
        },
        path,
    )


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.sim
@pytest.mark.slow
def test_viser_viewer_serves_its_page_on_a_smoke_checkpoint(tmp_path):
    """``python -m march.play ... viewer=viser`` headless: the URL line is printed, the page is
    served (viser's client), the policy steps, and Ctrl-C stops it cleanly."""
    import os
    import signal
    import time
    import urllib.request

    torch.set_num_threads(1)
    ckpt = tmp_path / "student.pt"
    _smoke_student(ckpt)
    port = _free_port()
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "march.play", f"student_ckpt={ckpt}", "compute=smoke",
         "viewer=viser", f"port={port}"],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
    )  # fmt: skip
    lines = []
    try:
        deadline = time.time() + 600
        while time.time() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            if "mjlab's viewer at http://" in line:
                break
        assert any(f"http://localhost:{port}" in x for x in lines), "".join(lines[-20:])
        page = urllib.request.urlopen(f"http://localhost:{port}/", timeout=30).read().decode()
        assert "<html" in page.lower() and "<script" in page.lower()
        time.sleep(3.0)  # let the policy step
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, rest[-2000:]
    closed = [x for x in rest.splitlines() if x.startswith("[play] viewer closed after")]
    assert closed and int(closed[0].split()[4]) > 0
