"""What the policy sees: the sim2sim runner's observation against the training env's, term by term.

The mjlab evaluation env (mujoco_warp; DR, depth corruption and proprioception noise off) runs
the smoke student with the **torch** policy on the hardware course (1 env) and on stone courses of
three levels (3 envs: the easiest, middle and hardest level), each for two episodes through
``env.reset()``: one from standing, one from a perturbed start (random root and joint velocities,
joint offsets), plus the env's own auto-resets after falls. Every control step is recorded: the
physics state, the ``student`` observation (history, raw units), the depth image, the action.

The runner then shadows that trajectory: at every step it takes the env's physics state
(qpos, qvel: the state, not the observation) and builds its own observation as on the robot - its
own history, previous action (from its own **ONNX** call), command from the heading, depth by ray
casting, ``start()`` where the env reset. Each term (every history slot) is compared with the
env's in raw units, and the ONNX action with the torch action (the ONNX fed the env's depth
image, so that a ray grazing a stone edge, compared in the depth term, does not move the
actions). The tolerances below are a few times the largest honest error measured on the smoke student (float32 warp vs float64 MuJoCo);
the planted faults show that a frame, sign, scale, order or one-step delay error in any single
term breaks the agreement.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest

pytestmark = pytest.mark.sim

STEPS_PER_EPISODE = 70
"""1.4 s per episode: the smoke student falls after ~1.2 s, so the env's auto-reset is crossed."""

TOLERANCE = {
    "base_ang_vel": 1e-5,
    "projected_gravity": 1e-6,
    "joint_pos": 5e-7,
    "joint_vel": 1e-6,
    "actions": 5e-6,
    "command": 1e-6,
    "depth": 2e-3,
    "action_out": 5e-6,
}
"""Max |runner - env| per term in raw units over every step and history slot (rad/s, 1, rad,
rad/s, 1, m/s | rad/s; depth: the largest pixel difference in normalised units, ``EDGE_PIXELS``
per image excused; ``action_out``: the ONNX action, fed the runner's proprioception and the env's
depth image, against the torch action). Largest honest error measured on the smoke student
(2026-12-01, 8 streams of 70 steps): base_ang_vel 1.7e-6, projected_gravity 1.2e-7, joint_pos
6.0e-8 (float32 rounding of qpos), joint_vel 0 (the state is copied), actions 6.6e-7 (the
runner's previous action is its own ONNX output), command 8.9e-8, depth 2.3e-4 (one pixel at a
stone edge), action_out 6.6e-7. Each tolerance is 6-11x that (joint_vel: float32 rounding of
the largest velocities)."""
EDGE_PIXELS = 2
"""Pixels per image excused from the depth tolerance: a ray that grazes a stone's edge can hit
its top in float32 (warp) and miss it in float64 (MuJoCo), a difference of the whole drop
behind the edge (measured 2026-12-04: one pixel of 768, 0.158, on one step of 840; every other
pixel within 2.3e-4). Every planted depth fault moves far more than two pixels of an image."""
MEASURED = {}
"""Filled by the test run and printed (pytest -s) for the record."""


@dataclass
class Stream:
    """One env's recorded trajectory: per step the state, the env's observation, the action."""

    course: str
    cell: dict[str, Any]
    qpos: list[np.ndarray] = field(default_factory=list)
    qvel: list[np.ndarray] = field(default_factory=list)
    student: list[np.ndarray] = field(default_factory=list)  # (H, P)
    depth: list[np.ndarray] = field(default_factory=list)  # (1, H, W)
    action: list[np.ndarray] = field(default_factory=list)  # torch, from this step's obs
    start: list[bool] = field(default_factory=list)  # the env (re)started the episode here


def _record(bundle, smoke_run, course: str, num_envs: int) -> list[Stream]:
    import torch
    from mjlab.envs import ManagerBasedRlEnv

    from march.config.cli import load
    from march.env.build import build_env_cfg
    from march.export.bundle import rebuild_student
    from march.sim2sim.deploy_bundle import Bundle
    from march.store.checkpoint import load_checkpoint
    from march.store.provenance import apply_checkpoint_config

    ckpt = str(smoke_run / "student" / "latest.pt")
    payload = load_checkpoint(ckpt, "student")
    overrides = ["eval.randomization=false", "eval.corruption=false", f"eval.course={course}"]
    cfg = apply_checkpoint_config(load(overrides), payload, overrides, ckpt, "student")
    policy = rebuild_student(payload, ckpt, cfg.student)
    env_cfg = build_env_cfg(cfg, "eval", num_envs=num_envs)
    env_cfg.observations["student"].enable_corruption = False
    env = ManagerBasedRlEnv(cfg=env_cfg, device="cpu")
    b = Bundle.load(bundle)
    terrain = env.scene.terrain
    if course == "stones":  # easiest, middle and hardest level, different columns
        rows = terrain.terrain_origins.shape[0]
        cols = terrain.terrain_origins.shape[1]
        levels = torch.tensor([0, rows // 2, rows - 1])[:num_envs]
        types = torch.arange(num_envs) % cols
        terrain.terrain_levels[:] = levels
        terrain.terrain_types[:] = types
        terrain.env_origins[:] = terrain.terrain_origins[levels, types]
    grid = b.spec["courses"][course]["cells"]
    cells = [
        grid[int(terrain.terrain_levels[i])][int(terrain.terrain_types[i])] for i in range(num_envs)
    ]
    for i, c in enumerate(cells):  # the bundle's cell is the env's
        np.testing.assert_allclose(env.scene.env_origins[i].numpy(), c["origin"], atol=1e-6)
    streams = []
    data = env.sim.data
    for perturbed in (False, True):
        if perturbed:
            base = env.event_manager.get_term_cfg("reset_base")
            base.params["velocity_range"] = {
                k: (-0.3, 0.3) for k in ("x", "y", "z", "roll", "pitch", "yaw")
            }
            joints = env.event_manager.get_term_cfg("reset_robot_joints")
            joints.params["position_range"] = (-0.1, 0.1)
            joints.params["velocity_range"] = (-1.0, 1.0)
        obs, _ = env.reset()
        ep = [Stream(course, cells[i]) for i in range(num_envs)]
        done = torch.ones(num_envs, dtype=torch.bool)
        for _ in range(STEPS_PER_EPISODE):
            command = env.command_manager.get_command("twist")
            with torch.no_grad():
                action = policy.act_inference(obs["student"], command, obs["depth"])
            for i, s in enumerate(ep):
                s.qpos.append(data.qpos[i].cpu().numpy().astype(np.float64))
                s.qvel.append(data.qvel[i].cpu().numpy().astype(np.float64))
                s.student.append(obs["student"][i].numpy().astype(np.float64))
                s.depth.append(obs["depth"][i].numpy())
                s.action.append(action[i].numpy().astype(np.float64))
                s.start.append(bool(done[i]))
            obs, _, terminated, truncated, _ = env.step(action)
            done = terminated | truncated
        streams += ep
    env.close()
    return streams


@pytest.fixture(scope="module")
def recording(bundle, smoke_run) -> list[Stream]:
    return _record(bundle, smoke_run, "hardware", 1) + _record(bundle, smoke_run, "stones", 3)


@pytest.fixture(scope="module")
def sims(bundle):
    from march.sim2sim.deploy_bundle import Bundle
    from march.sim2sim.runner import Sim2Sim

    b = Bundle.load(bundle)
    return {c: Sim2Sim(b, c) for c in ("hardware", "stones")}


# ---------------------------------------------------------------------------------------------
# Planted faults: one observation term of the runner made wrong in one way.


def _rot(sim) -> np.ndarray:
    return sim.data.xmat[sim.root_body].reshape(3, 3)


def _proprio_fault(term: str, kind: str):
    """A function (sim, values, previous values) -> values with ``term`` made wrong."""

    def swap(v):  # order: the first two elements (x <-> y; left hip pitch <-> roll; v_x <-> v_y)
        v = v.copy()
        v[[0, 1]] = v[[1, 0]]
        return v

    def frame(sim, v):
        if term in ("base_ang_vel", "projected_gravity"):  # world frame instead of the body's
            return _rot(sim) @ v
        if term == "joint_pos":  # absolute instead of relative to the default pose
            return v + sim.default
        if term == "actions":  # the joint target instead of the raw action
            return sim.offset + sim.scale * v
        if term == "command":  # (v_x, v_y) in the robot's heading frame instead of the course's
            yaw = np.arctan2(_rot(sim)[1, 0], _rot(sim)[0, 0])
            c, s = np.cos(yaw), np.sin(yaw)
            out = v.copy()
            out[:2] = [c * v[0] + s * v[1], -s * v[0] + c * v[1]]
            return out
        raise AssertionError(term)

    def apply(sim, values, previous):
        v = values[term]
        if kind == "frame":
            v = frame(sim, v)
        elif kind == "sign":
            v = -v
        elif kind == "scale":
            v = 1.1 * v
        elif kind == "order":
            v = swap(v)
        elif kind == "delay":
            v = previous[term] if previous is not None else v
        return {**values, term: v}

    return apply


def _depth_fault(kind: str):
    def apply(sim, image, previous):
        cam = sim.camera
        if kind == "frame":  # Euclidean range along the ray instead of planar depth
            planar = cam.planar(sim.model, sim.data)
            from march.sim2sim.depth_camera import normalize_depth

            rng = np.where(planar > 0, planar / cam.cos.reshape(planar.shape), 0.0)
            return normalize_depth(rng, cam.lo, cam.hi).astype(np.float32)[None, None]
        if kind == "sign":
            return 1.0 - image
        if kind == "scale":  # metres instead of normalised
            return image * (cam.hi - cam.lo) + cam.lo
        if kind == "order":  # upside down
            return image[..., ::-1, :].copy()
        if kind == "delay":
            return previous if previous is not None else image
        raise AssertionError(kind)

    return apply


TERMS = ("base_ang_vel", "projected_gravity", "joint_pos", "joint_vel", "actions", "command")
KINDS = ("frame", "sign", "scale", "order", "delay")
FAULTS = [
    (t, k) for t in (*TERMS, "depth") for k in KINDS if not (t == "joint_vel" and k == "frame")
]
"""Every (term, kind); joint velocities have no frame to get wrong."""


def _install(sim, fault):
    """Plant ``fault`` in this runner instance (restored by :func:`_remove`)."""
    if fault is None:
        return
    term, kind = fault
    state = {"prev": None}
    honest_start = sim.start

    def start(cell, delays=None):  # a delay that even forgets at reset: the hardest to see
        state["prev"] = None
        honest_start(cell, delays)

    sim.start = start
    if term == "depth":
        honest, f = sim.depth_image, _depth_fault(kind)

        def depth_image():
            image = honest()
            out = f(sim, image, state["prev"])
            state["prev"] = image
            return out

        sim.depth_image = depth_image
    else:
        honest, f = sim.term_values, _proprio_fault(term, kind)

        def term_values():
            values = honest()
            out = f(sim, values, state["prev"])
            state["prev"] = values
            return out

        sim.term_values = term_values


def _remove(sim):
    for name in ("depth_image", "term_values", "start"):
        sim.__dict__.pop(name, None)


# ---------------------------------------------------------------------------------------------
# The shadow replay.


def shadow(
    streams: list[Stream], sims: dict, fault=None, until: str | None = None
) -> dict[str, float]:
    """Max |runner - env| per term over every step and history slot of every stream.
    ``until``: stop at the first step where that term's error exceeds its tolerance (a planted
    fault's test needs only that; one that never shows still replays every step)."""
    err = dict.fromkeys((*TERMS, "depth", "action_out"), 0.0)
    for s in streams:
        sim = sims[s.course]
        _install(sim, fault)
        try:
            action = None
            for k in range(len(s.qpos)):
                sim.data.qpos[:] = s.qpos[k]
                sim.data.qvel[:] = s.qvel[k]
                if s.start[k]:
                    sim.start(s.cell)
                else:
                    sim.last_action = action
                    sim.observe()
                feeds = sim.inputs()
                depth_err = np.abs(feeds["depth"][0] - s.depth[k])
                # The policy's action from the runner's own proprioception and the env's depth
                # image: the ONNX-vs-torch comparison, and the previous-action term after it, are
                # then not moved by a grazing ray (the depth is compared on its own, below).
                action, _ = sim.act({**feeds, "depth": s.depth[k][None].astype(np.float32)})
                got = feeds["proprio_hist"][0].astype(np.float64)
                start = 0
                for name, dim in sim.terms:
                    d = np.abs(got[:, start : start + dim] - s.student[k][:, start : start + dim])
                    err[name] = max(err[name], float(d.max()))
                    start += dim
                err["depth"] = max(err["depth"], depth_beyond_edges(depth_err))
                err["action_out"] = max(
                    err["action_out"], float(np.abs(action - s.action[k]).max())
                )
                if until is not None and until in violations(err):
                    return err
        finally:
            _remove(sim)
    return err


def depth_beyond_edges(diff: np.ndarray) -> float:
    """The image's pixel difference with its ``EDGE_PIXELS`` largest left out (grazing rays):
    more than ``EDGE_PIXELS`` pixels beyond the depth tolerance make this value exceed it."""
    return float(np.sort(diff.ravel())[-(EDGE_PIXELS + 1)])


def violations(err: dict[str, float]) -> list[str]:
    return sorted(k for k, v in err.items() if not v <= TOLERANCE[k])


def test_the_recording_covers_what_the_issue_asks(recording):
    courses = {(s.course, s.cell["row"]) for s in recording}
    assert ("hardware", 0) in courses
    assert len({r for c, r in courses if c == "stones"}) >= 3  # three levels
    assert sum(s.start.count(True) for s in recording) > len(recording)  # auto-resets crossed
    moving = [np.abs(s.qvel[0]).max() for s in recording]
    assert min(moving) == 0.0 and max(moving) > 0.1  # from standing and from a perturbed start


def test_runner_sees_what_the_env_sees(recording, sims):
    err = shadow(recording, sims)
    MEASURED.update(err)
    print(
        "\nmeasured max |runner - env| per term: "
        + ", ".join(f"{k} {v:.2e}" for k, v in err.items())
    )
    assert violations(err) == [], err


@pytest.mark.parametrize("fault", FAULTS, ids=[f"{t}-{k}" for t, k in FAULTS])
def test_a_planted_fault_breaks_the_agreement(recording, sims, fault):
    err = shadow(recording, sims, fault, until=fault[0])
    bad = violations(err)
    term = fault[0]
    assert term in bad, f"{fault}: {term} error {err[term]:.2e} within {TOLERANCE[term]:.0e}"
