"""march.sim2sim: the exported student in plain MuJoCo, and its agreement with the mjlab env.

The first half needs no checkpoint and no simulator of the training stack (plain MuJoCo scenes
written here, hand-derived depths). The ``sim`` half exports the smoke run's student as a
deployment bundle, runs ``python -m march.sim2sim`` on it, and rolls the same ONNX student from
the same state in the mjlab evaluation env and in the plain-MuJoCo loop.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import mujoco
import numpy as np
import pytest

from march.sim2sim.command_line import Args, parse_args
from march.sim2sim.deploy_bundle import UsageError
from march.sim2sim.depth_camera import DepthCamera, camera_rays, normalize_depth
from march.sim2sim.runner import History

ROOT = Path(__file__).resolve().parent.parent
TRAINING_STACK = ("torch", "warp", "mujoco_warp", "mjlab", "hydra", "omegaconf", "rsl_rl")
"""Top-level packages the robot-side loop must not import."""
MARCH_ALLOWED = ("march", "march.sim2sim")
"""march modules it may import, with their submodules (march/__init__.py is one docstring and a
version)."""
MARCH_ALSO = ("march.store", "march.store.bounded_read")
"""The disk gate's bounded reads of a bundle (standard library only; march/store/__init__.py is
a docstring): the robot side reads its files through the same door as every tool."""


def run_py(code: str, timeout: int = 300) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=timeout
    )


def _allowed(name: str) -> bool:
    return (
        name == "march"
        or name in MARCH_ALSO
        or name == MARCH_ALLOWED[1]
        or name.startswith(MARCH_ALLOWED[1] + ".")
    )


def foreign_modules(names: list[str]) -> list[str]:
    return sorted(
        n
        for n in names
        if n.split(".")[0] in TRAINING_STACK or (n.startswith("march") and not _allowed(n))
    )


# ---------------------------------------------------------------------------------------------
# Pieces, no checkpoint.


def test_import_pulls_nothing_of_the_training_stack():
    res = run_py("import sys, json, march.sim2sim.runner; print(json.dumps(sorted(sys.modules)))")
    assert res.returncode == 0, res.stderr
    assert foreign_modules(json.loads(res.stdout)) == []


@pytest.mark.parametrize("w,h,fovy", [(32, 24, 55.2), (4, 2, 90.0), (7, 5, 30.0)])
def test_camera_rays_are_the_pinhole_through_pixel_centres(w, h, fovy):
    rays = camera_rays(w, h, fovy)
    assert rays.shape == (w * h, 3)
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0, atol=1e-12)
    t = math.tan(math.radians(fovy) / 2)
    # hand-derived: pixel (row i, col j) passes through ((2(j+.5)/w - 1) t w/h, (1 - 2(i+.5)/h) t)
    # on the image plane at distance 1 in front of the camera (-z)
    for i, j in [(0, 0), (h - 1, w - 1), (h // 2, 0), (0, w - 1)]:
        x = (2 * (j + 0.5) / w - 1) * t * w / h
        y = (1 - 2 * (i + 0.5) / h) * t
        r = rays[i * w + j]
        np.testing.assert_allclose(r[:2] / -r[2], [x, y], atol=1e-12)
    top, left = rays[0], rays[0]
    assert top[1] > 0 and left[0] < 0  # row 0 is the top of the image, column 0 the left
    # symmetric about the optical axis
    grid = rays.reshape(h, w, 3)
    np.testing.assert_allclose(grid[:, ::-1, 0], -grid[:, :, 0], atol=1e-12)
    np.testing.assert_allclose(grid[::-1, :, 1], -grid[:, :, 1], atol=1e-12)


def test_normalize_depth_hand_values():
    d = np.array([0.0, -1.0, np.nan, np.inf, 0.05, 0.1, 1.55, 3.0, 5.0])
    want = [1.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.5, 1.0, 1.0]
    np.testing.assert_allclose(normalize_depth(d, 0.1, 3.0), want, atol=1e-12)


def test_history_back_fills_then_slides_oldest_first():
    hist = History(3)
    hist.push(np.array([1.0, 10.0]))
    np.testing.assert_array_equal(hist.array()[0], [[1, 10]] * 3)
    hist.push(np.array([2.0, 20.0]))
    hist.push(np.array([3.0, 30.0]))
    hist.push(np.array([4.0, 40.0]))
    out = hist.array()
    assert out.shape == (1, 3, 2) and out.dtype == np.float32
    np.testing.assert_array_equal(out[0], [[2, 20], [3, 30], [4, 40]])


SCENE = """
<mujoco>
  <worldbody>
    <geom name="floor" type="plane" size="5 5 0.1" pos="0 0 {floor}" group="0"/>
    <geom name="robot_part" type="box" size="0.05 0.05 0.05" pos="0 0 {box}" group="3"/>
    <body name="torso" pos="0 0 {height}" euler="0 {pitch} 0">
      <freejoint/>
      <geom type="sphere" size="0.01" group="2" contype="0" conaffinity="0"/>
      <camera name="cam" fovy="{fovy}" resolution="8 6"/>
    </body>
  </worldbody>
</mujoco>
"""


def depth_spec(fovy: float, groups=(0,)) -> dict:
    return {
        "camera": "cam",
        "width": 8,
        "height": 6,
        "fovy_deg": fovy,
        "min_range_m": 0.1,
        "max_range_m": 3.0,
        "geom_groups": list(groups),
    }


@pytest.mark.parametrize("pitch_deg", [0.0, 20.0, -35.0])
@pytest.mark.parametrize("height", [0.7, 1.3])
def test_ray_cast_depth_is_planar_and_sees_only_enabled_groups(height, pitch_deg):
    """A camera ``height`` above a floor, looking down and pitched about its x axis: the planar
    depth of pixel ray r (camera frame) is the hit distance h / (-r_world,z) times cos(r, -z_cam);
    a group-3 box right under the camera is invisible to a group-0 camera."""
    fovy = 55.2
    xml = SCENE.format(floor=0.0, box=height - 0.3, height=height, pitch=pitch_deg, fovy=fovy)
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    cam = DepthCamera(model, depth_spec(fovy))
    got = cam.planar(model, data)
    rays = camera_rays(8, 6, fovy)
    xmat = data.cam_xmat[0].reshape(3, 3)
    world = rays @ xmat.T
    assert (world[:, 2] < 0).all()  # every ray goes down to the floor
    dist = height / -world[:, 2]
    want = (dist * -rays[:, 2]).reshape(6, 8)
    # a hit past the ray-cast cutoff reads 0 (no return): it normalises to 1 either way
    far = (dist >= cam.cutoff * (1.0 - 1e-9)).reshape(6, 8)
    assert np.all(np.where(far, True, want < cam.hi / cam.cos.min()))
    np.testing.assert_allclose(np.where(far, 0.0, got), np.where(far, 0.0, want), atol=1e-9)
    if pitch_deg == 0.0:  # looking straight down at a plane: planar depth is the height
        np.testing.assert_allclose(got, height, atol=1e-9)
    image = cam.image(model, data)
    assert image.shape == (1, 1, 6, 8) and image.dtype == np.float32
    np.testing.assert_allclose(image[0, 0], normalize_depth(got, 0.1, 3.0), atol=1e-6)
    if pitch_deg == 0.0:  # with group 3 enabled the box under the camera is seen
        cam3 = DepthCamera(model, depth_spec(fovy, groups=(0, 3)))
        np.testing.assert_allclose(cam3.planar(model, data)[2:4, 3:5], 0.25, atol=1e-9)


def test_nothing_within_range_reads_one():
    xml = SCENE.format(floor=-10.0, box=-20.0, height=0.0, pitch=0.0, fovy=55.2)
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    image = DepthCamera(model, depth_spec(55.2)).image(model, data)
    np.testing.assert_array_equal(image, 1.0)


@pytest.mark.parametrize(
    "argv,message",
    [
        ([], "give onnx="),
        (["onnx=a.onnx", "bogus=1"], "unknown key 'bogus'"),
        (["onnx=a.onnx", "seed=x"], "seed=x: not a int"),
        (["onnx=a.onnx", "course=moon"], "course=moon"),
        (["onnx=a.onnx", "difficulty=1.5"], "difficulty=1.5"),
        (["onnx=a.onnx", "seconds=0"], "seconds=0"),
        (["onnx=a.onnx", "threads=0"], "threads=0"),
        (["onnx=a.onnx", "out=video.avi"], "out=video.avi"),
        (["onnx=a.onnx", "stones"], "expected key=value"),
    ],
)
def test_bad_arguments_are_one_clear_error(argv, message):
    with pytest.raises(UsageError, match=message.replace("(", r"\(")):
        parse_args(argv)


def test_arguments_parse_to_types():
    args = parse_args(["onnx=x.onnx", "course=stones", "difficulty=0.25", "seed=7", "seconds=3"])
    assert args == Args(onnx="x.onnx", course="stones", difficulty=0.25, seed=7, seconds=3.0)


def test_cli_missing_file_is_one_line_exit_2(tmp_path):
    res = subprocess.run(
        [sys.executable, "-m", "march.sim2sim", f"onnx={tmp_path / 'nope.onnx'}"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode == 2
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "no such file" in lines[0]


# ---------------------------------------------------------------------------------------------
# The real thing: the smoke run's student, exported, in plain MuJoCo and in the mjlab env.

AGREEMENT_STEPS = 25
"""0.5 s of control at 50 Hz."""
JOINT_TOL_RAD = 1e-3
"""Joint-trajectory agreement over those steps. Measured on the smoke student (2026-11-30):
max |q_mjlab - q_mujoco| = 2.3e-6 rad over 0.5 s (4e-4 rad after 1 s); see README."""
ROOT_TOL_M = 1e-3
"""Root position agreement over those steps (measured 1e-6 m)."""
DEPTH_MAD_TOL = 1e-4
"""Mean |depth_mjlab - depth_mujoco| of the normalised image at the same pose (measured 3e-8)."""


@pytest.mark.sim
def test_bundle_is_self_describing(bundle):
    from march.sim2sim.deploy_bundle import Bundle

    spec = json.loads(bundle.with_suffix(".deploy.json").read_text())
    assert spec["format"] == 3 and spec["onnx"]["file"] == "student.onnx"
    assert spec["rates"]["decimation"] * spec["rates"]["physics_dt_s"] == pytest.approx(0.02)
    assert len(spec["action"]["joint_names"]) == len(spec["action"]["scale"]) == 29
    assert [t["name"] for t in spec["observation"]["proprio_terms"]] == [
        "base_ang_vel",
        "projected_gravity",
        "joint_pos",
        "joint_vel",
        "actions",
        "command",
    ]
    assert spec["depth"]["width"] == 32 and spec["depth"]["height"] == 24
    hw = spec["courses"]["hardware"]["cells"]
    assert len(hw) == 1 and len(hw[0]) == 1
    assert sum(1 for b in hw[0][0]["boxes"] if b[5] == 1) == 4  # the hardware course's stones
    stones = spec["courses"]["stones"]["cells"]
    assert len(stones) > 1 and stones[-1][0]["difficulty"] == pytest.approx(1.0)
    b = Bundle.load(bundle)
    for course in ("hardware", "stones"):
        model = b.scene(course)
        assert model.nu == 29 and model.opt.timestep == spec["rates"]["physics_dt_s"]


@pytest.mark.sim
@pytest.mark.parametrize("course", ["hardware", "stones"])
def test_cli_prints_one_json_and_imports_nothing_of_training(bundle, course):
    code = (
        "import sys, json\n"
        "from march.sim2sim.command_line import main\n"
        f"main(['onnx={bundle}', 'course={course}', 'seconds=1', 'seed=1', 'difficulty=0.3'])\n"
        "print(json.dumps(sorted(sys.modules)))\n"
    )
    res = run_py(code)
    assert res.returncode == 0, res.stderr[-2000:]
    lines = res.stdout.strip().splitlines()
    assert len(lines) == 2
    row = json.loads(lines[0])
    assert foreign_modules(json.loads(lines[1])) == []
    for key in ("distance_m", "success", "abs_torque_nm", "abs_ang_jerk", "steps"):
        assert key in row
    assert 1 <= row["steps"] <= 50 and row["steps"] == round(row["seconds_simulated"] / 0.02)
    assert 0.0 <= row["distance_m"] < row["goal_distance_m"]
    assert row["success"] is False  # 1 s is too short to reach the goal
    assert row["abs_torque_nm"] > 0.0 and row["ms_per_policy_call"] > 0.0
    if course == "stones":  # difficulty 0.3 -> the nearest level, column seed mod columns
        assert row["cell"][1] == 1 and abs(row["difficulty"] - 0.3) <= 0.06


@pytest.mark.sim
def test_video_is_written_or_refused_in_one_line(bundle, tmp_path):
    """With an OpenGL backend (MUJOCO_GL=egl as in mjlab) a short rollout films; without one
    the command refuses in one line before simulating."""
    probe = run_py(
        "import march.sim2sim.runner, mujoco\n"
        "m = mujoco.MjModel.from_xml_string('<mujoco/>')\n"
        "mujoco.Renderer(m, 8, 8)\n"
    )
    video = tmp_path / "v.gif"
    res = subprocess.run(
        [sys.executable, "-m", "march.sim2sim", f"onnx={bundle}", "seconds=0.1", f"out={video}"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    if probe.returncode == 0:
        assert res.returncode == 0, res.stderr[-2000:]
        assert json.loads(res.stdout)["video"] == str(video)
        from PIL import Image

        with Image.open(video) as img:
            assert img.size == (320, 240) and img.n_frames == 5  # 0.1 s at 50 Hz
    else:
        assert res.returncode == 2
        lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
        assert len(lines) == 1 and "no OpenGL context" in lines[0]
        assert not video.exists()


@pytest.mark.sim
def test_agreement_with_the_mjlab_eval_env(bundle, smoke_run):
    """Same ONNX student, same initial state: mjlab's evaluation env (warp, DR and corruption
    off, hardware course) against the plain-MuJoCo loop, over the first 0.5 s."""
    import torch
    from mjlab.envs import ManagerBasedRlEnv
    from smoke_student import hardware_eval_cfg

    from march.sim2sim.deploy_bundle import Bundle
    from march.sim2sim.runner import Sim2Sim, policy_session

    cfg, env_cfg = hardware_eval_cfg(smoke_run)
    env = ManagerBasedRlEnv(cfg=env_cfg, device="cpu")
    b = Bundle.load(bundle)
    sim = Sim2Sim(b, "hardware")
    cell = b.cell("hardware", 0.0, 0)

    # 1. The scene is the env's compiled model, field for field.
    ref, got = env.sim.mj_model, sim.model
    for name in (
        "body_mass",
        "body_inertia",
        "body_ipos",
        "body_pos",
        "body_quat",
        "jnt_range",
        "dof_armature",
        "dof_damping",
        "dof_frictionloss",
        "actuator_gainprm",
        "actuator_biasprm",
        "actuator_forcerange",
        "actuator_trnid",
        "geom_size",
        "geom_pos",
        "geom_friction",
        "geom_solref",
        "geom_solimp",
        "geom_group",
        "cam_pos",
        "cam_quat",
        "cam_fovy",
    ):
        np.testing.assert_array_equal(getattr(got, name), getattr(ref, name), err_msg=name)
    for name in ("timestep", "iterations", "ls_iterations", "integrator", "cone", "solver"):
        assert getattr(got.opt, name) == getattr(ref.opt, name), name
    term = env.action_manager.get_term("joint_pos")
    assert list(term._target_names) == [
        n.removeprefix("robot/") for n in b.spec["action"]["joint_names"]
    ]
    np.testing.assert_allclose(term.scale[0].numpy(), b.spec["action"]["scale"], atol=1e-6)
    np.testing.assert_allclose(term.offset[0].numpy(), b.spec["action"]["offset"], atol=1e-6)
    assert env.observation_manager.active_terms["student"] == [
        t["name"] for t in b.spec["observation"]["proprio_terms"]
    ]
    np.testing.assert_allclose(env.scene.env_origins[0].numpy(), cell["origin"], atol=1e-6)

    # 2. The same state in both: the env's reset state copied into MuJoCo.
    obs, _ = env.reset()
    data = env.sim.data
    sim.data.qpos[:] = data.qpos[0].cpu().numpy()
    sim.data.qvel[:] = data.qvel[0].cpu().numpy()
    sim.start(cell)
    np.testing.assert_allclose(sim.history.array()[0], obs["student"][0].numpy(), atol=1e-6)

    session = policy_session(b.onnx_path)
    probe = mujoco.MjData(sim.model)
    joint_err, root_err, depth_mad = [], [], []
    for _ in range(AGREEMENT_STEPS):
        # the env's depth image against MuJoCo's ray casting at the env's own pose
        probe.qpos[:] = data.qpos[0].cpu().numpy()
        mujoco.mj_forward(sim.model, probe)
        env_depth = obs["depth"][0].numpy()
        depth_mad.append(float(np.abs(sim.camera.image(sim.model, probe)[0] - env_depth).mean()))
        feeds = {
            "proprio_hist": obs["student"].numpy(),
            "command": env.command_manager.get_command("twist").numpy(),
            "depth": obs["depth"].numpy(),
        }
        action_env = session.run(["actions"], feeds)[0]
        action_sim, _ = sim.act(sim.inputs())
        obs, _, terminated, truncated, _ = env.step(torch.as_tensor(action_env))
        assert not bool(terminated | truncated), "the env episode ended within 0.5 s"
        sim.step(action_sim)
        q_env = data.qpos[0].cpu().numpy()
        joint_err.append(float(np.abs(q_env[sim.qadr] - sim.data.qpos[sim.qadr]).max()))
        root_err.append(float(np.abs(q_env[:3] - sim.data.qpos[:3]).max()))
    print(
        f"\nagreement over {AGREEMENT_STEPS} steps: max joint {max(joint_err):.2e} rad, "
        f"max root {max(root_err):.2e} m, depth MAD mean {np.mean(depth_mad):.2e} "
        f"max {max(depth_mad):.2e}"
    )
    assert max(joint_err) < JOINT_TOL_RAD, joint_err
    assert max(root_err) < ROOT_TOL_M, root_err
    assert max(depth_mad) < DEPTH_MAD_TOL, depth_mad
    env.close()
