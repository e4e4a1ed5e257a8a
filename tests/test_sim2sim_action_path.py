"""What the policy's action does: the sim2sim runner's ``step()`` against mjlab's action manager.

The mjlab evaluation env (mujoco_warp, 4 envs on the hardware course, DR off except the control
delay: the training's actuator delay buffer, with the lags 0, 1, 3 and 4 physics steps set at the
first reset and redrawn by the ``control_delay`` event at every auto-reset) is driven by
**scripted** actions, not the smoke student's: per control step a seeded draw per joint whose
amplitude cycles through 0.2, 1, 3 and 6 (targets up to ~3 rad past the default pose, so the
motors run into their torque limits - checked - and any clip of the stored action shows). Every
physics step records the env's ``data.ctrl`` (the delayed position targets as the actuators get
them); every control step the raw action the action manager stores (the next observation's
previous action), the lag in effect and whether the env reset.

The runner then replays the same actions from the same states (qpos, qvel copied at every
control step; ``start()`` where the env reset, with the env's lag): its ``step()`` must write the
same ``data.ctrl`` before every ``mj_step`` and keep the same previous action (raw, unclipped) in
``last_action`` and in its observation. Each fault planted in the runner (action scale applied
twice, the arms' default offset omitted, one motor pair swapped in the action only, the stored
action clipped to +-0.4, the command delay one physics step long, a permuted ``motor_index``
table in the bundle) breaks the agreement.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest

pytestmark = pytest.mark.sim

LAGS = (0, 1, 3, 4)
"""Control delay per env at the first reset [physics steps] (0-20 ms at 5 ms)."""
STEPS = 48
AMPLITUDES = (0.2, 1.0, 3.0, 6.0)
TOL_CTRL = 2e-6
"""|runner - env| of a position target [rad]: the env holds them in float32 (targets up to
~5 rad: float32 spacing 4.8e-7); measured 0 to 4.8e-7."""
TOL_ACTION = 1e-6
"""|runner - env| of the stored previous action (float32 in the env)."""


@dataclass
class Stream:
    cell: dict[str, Any]
    qpos: list[np.ndarray] = field(default_factory=list)
    qvel: list[np.ndarray] = field(default_factory=list)
    action: list[np.ndarray] = field(default_factory=list)
    start: list[bool] = field(default_factory=list)  # the env (re)started the episode here
    lag: list[int] = field(default_factory=list)  # the lag in effect during this step
    ctrl: list[np.ndarray] = field(default_factory=list)  # (decimation, nu) per step
    stored: list[np.ndarray] = field(default_factory=list)  # action manager's raw action after
    obs_action: list[np.ndarray] = field(default_factory=list)  # "actions" of the next obs
    done: list[bool] = field(default_factory=list)


def scripted_actions(num_actions: int, seed: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [
        AMPLITUDES[k % len(AMPLITUDES)] * rng.uniform(-1.0, 1.0, num_actions) for k in range(STEPS)
    ]


def _record(bundle, smoke_run) -> list[Stream]:
    import torch
    from mjlab.envs import ManagerBasedRlEnv
    from mjlab.managers.event_manager import EventTermCfg
    from mjlab.managers.scene_entity_config import SceneEntityCfg

    from march.config.cli import load
    from march.env.build import PROPRIO_TERMS, build_env_cfg
    from march.env.dr_terms import control_delay_lags, install_control_delay, sample_control_delay
    from march.sim2sim.deploy_bundle import Bundle
    from march.store.checkpoint import load_checkpoint
    from march.store.provenance import apply_checkpoint_config

    ckpt = str(smoke_run / "student" / "latest.pt")
    payload = load_checkpoint(ckpt, "student")
    overrides = ["eval.randomization=false", "eval.corruption=false", "eval.course=hardware"]
    cfg = apply_checkpoint_config(load(overrides), payload, overrides, ckpt, "student")
    n = len(LAGS)
    env_cfg = build_env_cfg(cfg, "eval", num_envs=n)
    env_cfg.observations["student"].enable_corruption = False
    assert install_control_delay(env_cfg, cfg.dr) >= max(LAGS)  # the training's buffer
    env_cfg.events["control_delay"] = EventTermCfg(
        func=sample_control_delay,
        mode="reset",
        params={"asset_cfg": SceneEntityCfg("robot"), "delay_ms": tuple(cfg.dr.control_delay_ms)},
    )
    env = ManagerBasedRlEnv(cfg=env_cfg, device="cpu")
    b = Bundle.load(bundle)
    cell = b.spec["courses"]["hardware"]["cells"][0][0]
    data = env.sim.data
    physics: list[np.ndarray] = []
    honest_step = env.sim.step

    def step_and_record():
        physics.append(data.ctrl.cpu().numpy().astype(np.float64).copy())
        honest_step()

    env.sim.step = step_and_record
    obs, _ = env.reset()
    robot = env.scene["robot"]
    for act in robot.actuators:
        if act.has_delay:
            act.set_lags(torch.tensor(LAGS), torch.arange(n))
    a = len(b.spec["joints"])
    dims = dict.fromkeys(PROPRIO_TERMS, 3) | {"joint_pos": a, "joint_vel": a, "actions": a}
    start = sum(dims[t] for t in PROPRIO_TERMS[: PROPRIO_TERMS.index("actions")])
    scripts = [scripted_actions(a, seed) for seed in range(n)]
    streams = [Stream(cell) for _ in range(n)]
    done = torch.ones(n, dtype=torch.bool)
    term = env.action_manager.get_term("joint_pos")
    for k in range(STEPS):
        lags = control_delay_lags(env)
        for i, s in enumerate(streams):
            s.qpos.append(data.qpos[i].cpu().numpy().astype(np.float64))
            s.qvel.append(data.qvel[i].cpu().numpy().astype(np.float64))
            s.action.append(scripts[i][k])
            s.start.append(bool(done[i]))
            s.lag.append(int(lags[i]))
        physics.clear()
        action = torch.tensor(np.stack([sc[k] for sc in scripts]), dtype=torch.float32)
        obs, _, terminated, truncated, _ = env.step(action)
        done = terminated | truncated
        ctrl = np.stack(physics)  # (decimation, n, nu)
        for i, s in enumerate(streams):
            s.ctrl.append(ctrl[:, i])
            s.stored.append(term.raw_action[i].cpu().numpy().astype(np.float64))
            s.obs_action.append(obs["student"][i, -1, start : start + a].numpy().astype(float))
            s.done.append(bool(done[i]))
    env.close()
    return streams


@pytest.fixture(scope="module")
def recording(bundle, smoke_run) -> list[Stream]:
    return _record(bundle, smoke_run)


@pytest.fixture(scope="module")
def loaded(bundle):
    from march.sim2sim.deploy_bundle import Bundle

    return Bundle.load(bundle)


def _sim(b):
    from march.sim2sim.runner import Sim2Sim

    return Sim2Sim(b, "hardware")


def replay(streams: list[Stream], sim, monkeypatch) -> dict[str, float]:
    """Max |runner - env| of the physics-step targets and of the stored previous action."""
    import mujoco

    from march.sim2sim import runner
    from march.sim2sim.runner import Delays

    applied: list[np.ndarray] = []
    honest = mujoco.mj_step

    def mj_step(m, d):
        applied.append(d.ctrl.copy())
        honest(m, d)

    monkeypatch.setattr(runner.mujoco, "mj_step", mj_step)
    err = {"ctrl": 0.0, "stored_action": 0.0, "obs_action": 0.0, "saturated": 0.0}
    try:
        for s in streams:
            for k in range(len(s.action)):
                sim.data.qpos[:] = s.qpos[k]
                sim.data.qvel[:] = s.qvel[k]
                if s.start[k]:
                    sim.start(s.cell, Delays(control_lag=s.lag[k]))
                applied.clear()
                sim.step(s.action[k])
                got = np.stack(applied)
                err["ctrl"] = max(err["ctrl"], float(np.abs(got - s.ctrl[k]).max()))
                force = np.abs(sim.data.actuator_force[sim.act_ids])
                limit = sim.model.actuator_forcerange[sim.act_ids, 1]
                err["saturated"] += float((force >= limit - 1e-9).sum())
                if s.done[k]:  # the env reset after this step: its stored action is 0 now
                    continue
                err["stored_action"] = max(
                    err["stored_action"], float(np.abs(sim.last_action - s.stored[k]).max())
                )
                mine = sim.history.frames[-1]
                lo = sum(d for name, d in sim.terms[: [t for t, _ in sim.terms].index("actions")])
                err["obs_action"] = max(
                    err["obs_action"],
                    float(np.abs(mine[lo : lo + len(sim.act_ids)] - s.obs_action[k]).max()),
                )
    finally:
        monkeypatch.setattr(runner.mujoco, "mj_step", honest)
    return err


def bad(err: dict[str, float]) -> list[str]:
    out = []
    if not err["ctrl"] <= TOL_CTRL:
        out.append("ctrl")
    for key in ("stored_action", "obs_action"):
        if not err[key] <= TOL_ACTION:
            out.append(key)
    return out


def test_the_recording_covers_what_the_issue_asks(recording):
    assert {s.lag[0] for s in recording} == set(LAGS)
    assert sum(s.start.count(True) for s in recording) > len(recording)  # auto-resets crossed
    biggest = max(float(np.abs(a).max()) for s in recording for a in s.action)
    assert biggest > 4.0  # far past any +-0.4 or +-1 clip


def test_runner_step_writes_what_the_action_manager_writes(recording, loaded, monkeypatch):
    err = replay(recording, _sim(loaded), monkeypatch)
    print("\naction path: " + ", ".join(f"{k} {v:.2e}" for k, v in err.items()))
    assert bad(err) == [], err
    assert err["saturated"] > 0  # the scripted actions drive motors into their torque limits


# ---------------------------------------------------------------------------------------------
# Planted faults: the runner's action path made wrong in one way each.

ARM_WORDS = ("shoulder", "elbow", "wrist")
SWAP = ("left_ankle_pitch_joint", "left_ankle_roll_joint")


def _plant(sim, fault: str) -> None:
    names = list(sim.spec["robot"]["joint_names"])
    if fault == "scale_twice":
        sim.joint_targets = lambda a: sim.offset + sim.scale * (sim.scale * a)
    elif fault == "arm_offset_omitted":
        keep = np.array([not any(w in n for w in ARM_WORDS) for n in names], dtype=float)
        sim.joint_targets = lambda a: keep * sim.offset + sim.scale * a
    elif fault == "motor_pair_swapped":
        i, j = (names.index(n) for n in SWAP)

        def swapped(a):
            a = a.copy()
            a[[i, j]] = a[[j, i]]
            return sim.offset + sim.scale * a

        sim.joint_targets = swapped
    elif fault == "previous_action_clipped":
        sim.stored_action = lambda a: np.clip(a, -0.4, 0.4)
    elif fault == "delay_one_step_long":
        honest = sim.start

        def start(cell, delays=None):
            from march.sim2sim.runner import Delays

            lag = delays.control_lag if delays is not None else 0
            honest(cell, Delays(control_lag=lag + 1))

        sim.start = start
    else:
        raise AssertionError(fault)


FAULTS = (
    "scale_twice",
    "arm_offset_omitted",
    "motor_pair_swapped",
    "previous_action_clipped",
    "delay_one_step_long",
)


@pytest.mark.parametrize("fault", FAULTS)
def test_a_planted_action_fault_breaks_the_agreement(recording, loaded, monkeypatch, fault):
    sim = _sim(loaded)
    _plant(sim, fault)
    err = replay(recording, sim, monkeypatch)
    print(f"\n{fault}: " + ", ".join(f"{k} {v:.2e}" for k, v in err.items()))
    assert bad(err), f"{fault} passed the action-path test: {err}"


def test_a_permuted_motor_table_is_caught(recording, loaded, monkeypatch):
    """motor_index is the map the runner uses: swap two slots in the bundle's table (the
    simulated robot's wiring stays Unitree's) and the targets land on the wrong motors."""
    from march.sim2sim.deploy_bundle import Bundle

    rng = np.random.default_rng(0)
    for _ in range(3):
        spec = copy.deepcopy(loaded.spec)
        i, j = rng.choice(len(spec["joints"]), 2, replace=False)
        a, b = spec["joints"][i]["motor_index"], spec["joints"][j]["motor_index"]
        spec["joints"][i]["motor_index"], spec["joints"][j]["motor_index"] = b, a
        err = replay(recording, _sim(Bundle(loaded.onnx_path, spec)), monkeypatch)
        assert "ctrl" in bad(err), (i, j, err)
