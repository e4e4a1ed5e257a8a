"""Every configuration value is checked when the config is composed (issue 12, item 7).

The schema (``MarchConfig`` and its sections, ``march.world.courses.CourseCfg`` included) is walked
field by field: every leaf must have out-of-domain values below (``BAD``) or be listed in
``FREE`` with the reason it has no domain beyond its type, so a field added later without checks
fails here. Each bad value must raise one :class:`ConfigError` line naming the key and the value;
the boundary values in ``GOOD`` must still be accepted. Generated cases add ``nan``/``inf`` for
every float and a wrong length for every fixed-size tuple. A few cases go through the real
command line (``python -m march.train``): exit 2, one line on stderr, no traceback, before any
simulation.
"""

from __future__ import annotations

import copy
import subprocess
import sys
from dataclasses import fields, is_dataclass
from pathlib import Path
from typing import Any, get_args, get_origin, get_type_hints

import pytest
import torch
from omegaconf import OmegaConf

from march.config import SEED_MAX, ConfigError, MarchConfig, cnn_output_hw, to_march_config
from march.config.cli import compose
from march.policies.student import StudentPolicy

ROOT = Path(__file__).resolve().parent.parent
NAN, INF = float("nan"), float("inf")

# Out-of-domain values per key (the smoke preset is the base config).
BAD: dict[str, list[Any]] = {
    "seed": [-1, SEED_MAX + 1, 2**32 - 1],
    "stage": ["train"],
    "objective": ["mean_speed", "distance_m"],
    "teacher_ckpt": [""],
    "student_ckpt": [""],
    "resume": [""],
    "out": [""],
    "compute.name": ["tpu"],
    "compute.device": ["gpu", "cuda:x", "cuda0"],
    "compute.compile_mode": ["max-autotune", "reduce_overhead"],
    "compute.num_envs": [0, -4],
    "compute.eval_num_envs": [0],
    "compute.torch_threads": [-1],
    "compute.dist_timeout_s": [0, -5.0],
    "env.episode_length_s": [0.0, -1.0, 0.01],  # 0.01 s < one control step (0.02 s)
    "env.sim_dt": [0.0, -0.005],
    "env.decimation": [0],
    "env.history_length": [0],
    "env.command_vx": [[0.8, 0.3], [0.3, 0.5, 0.8]],
    "env.command_vy": [[0.1, -0.1], [0.0]],
    "env.command_yaw_rate": [[0.2, -0.2], [0.1, 0.2]],  # reversed; without 0
    "env.command_heading_stiffness": [-0.5],
    "depth.name": [""],
    "depth.width": [0, -32],
    "depth.height": [0],
    "depth.fovy": [0.0, 180.0, -10.0],
    "depth.min_range": [-0.1, 3.0, 5.0],  # >= max_range (3.0)
    "depth.max_range": [0.0, -1.0],
    "depth.pos": [[0.0, 0.0]],
    "depth.pitch_deg": [91.0, -120.0],
    "depth.geom_groups": [[], [6], [-1]],
    "depth.noise_scale": [-0.1],
    "depth.dropout": [1.0, -0.05],
    "depth.delay_steps": [[2, 1], [-1, 0], [0, 1, 2]],
    "reward.name": ["dense reward", "1arm", ""],  # a name labels dirs and figures
    "reward.terms": [{"anything": INF}],
    "termination.tilt_limit_deg": [0.0, 181.0],
    "termination.min_base_height_m": [-0.1],
    "termination.max_foot_drop_m": [0.0],
    "extra_modules": [["my lab.terms"], ["1x"]],
    "curriculum.name": ["random"],
    "curriculum.num_levels": [0],
    "curriculum.num_cols": [0],
    "curriculum.max_init_level": [-1, 10],  # num_levels = 10
    "curriculum.flat_levels": [-1, 10],
    "curriculum.terrain_seed": [-1, SEED_MAX + 1],
    "curriculum.promote_fraction": [2.0, 1.01, 0.0, -0.5],
    "curriculum.demote_fraction": [-0.1, 1.0],  # must stay below promote_fraction (1.0)
    "student.variant": ["big net", ""],
    "student.image": ["rgb"],
    "student.fusion": ["attention"],
    "student.head": ["gmm"],
    "figures.compare": [["clf"], ["clf:clf"], ["a:b:c"]],
    "figures.reference_variant": ["no variant"],
    "figures.ablation_teacher": [""],
    "student.cnn_channels": [[], [24, 0, 48, 64]],
    "student.cnn_kernels": [[5, 0, 3, 3], [5, 3, 3]],
    "student.cnn_strides": [[1, 0, 2, 1]],
    "student.d_model": [0, 100],  # 100 is not divisible by n_heads = 8
    "student.n_heads": [0, 7],
    "student.n_layers": [0],
    "student.dim_feedforward": [0],
    "student.fusion_mlp": [[512, 0]],
    "student.head_hidden": [[-1]],
    "student.num_modes": [0],
    "student.min_std": [0.0],
    "student.log_std_min": [2.0, 5.0],
    "student.log_std_max": [-3.0],
    "student.init_log_std": [-3.5, 2.5],
    "student.activation": ["softmax"],
    "student.huber_delta": [0.0],
    "student.normalizer_eps": [0.0, -1e-2],
    "teacher.max_iterations": [0],
    "teacher.budget_scale": [0.0, -2.0],
    "teacher.num_steps_per_env": [0],
    "teacher.hidden_dims": [[], [512, 0]],
    "teacher.activation": ["softmax"],
    "teacher.init_std": [0.0],
    "teacher.init_std_legs": [0.0, -1.0],
    "teacher.init_std_waist": [0.0],
    "teacher.init_std_arms": [-0.5],
    "reference.com_anchoring": ["orbit"],
    "reference.com_height": ["low"],
    "reference.com_height_free_step": [-0.1],
    "reference.com_height_slope": [-1.0],
    "reference.com_height_min": [0.2, 0.8],
    "reference.swing_toe_down": [-1.5, 1.01],
    "reference.swing_height": [0.01, 0.31],
    "reference.swing_toe_roll": [-1.01, 1.5],
    "reference.swing_xy_shape": [-0.01, 0.51],
    "reference.swing_pitch_carry": [-0.01, 1.01],
    "reference.swing_roll_out": [-0.51, 0.6],
    "reference.swing_heel_strike": [-0.01, 0.51],
    "teacher.learning_rate": [0.0, -1e-4],
    "teacher.schedule": ["cosine"],
    "teacher.num_learning_epochs": [0],
    "teacher.num_mini_batches": [0, 33],  # smoke: 4 envs x 8 steps = 32 samples
    "teacher.clip_param": [0.0],
    "teacher.value_loss_coef": [-1.0],
    "teacher.entropy_coef": [-0.01],
    "teacher.gamma": [1.5, -0.1],
    "teacher.lam": [1.01],
    "teacher.desired_kl": [0.0],
    "teacher.max_grad_norm": [0.0],
    "teacher.save_interval": [0],
    "teacher.eval_interval": [-1],
    "teacher.max_nonfinite_updates": [0, -1],
    "distill.max_iterations": [0],
    "distill.num_steps_per_env": [0],
    "distill.learning_rate": [0.0],
    "distill.num_learning_epochs": [0],
    "distill.gradient_length": [0],
    "distill.max_grad_norm": [-1.0],
    "distill.teacher_samples": [0],
    "distill.teacher_std_scale": [-0.1],
    "distill.eval_interval": [-1],
    "distill.save_interval": [0],
    "distill.max_nonfinite_updates": [0],
    "eval.num_rollouts": [0],
    "eval.episode_length_s": [0.0],
    "eval.course": ["moon"],
    "eval.command_vx": [0.0, 0.9],  # outside env.command_vx = [0.3, 0.8]
    "eval.policy": ["expert"],
    "eval.terrain_seed": [-1, SEED_MAX + 1],
    "logger.name": ["mlflow"],
    "logger.project": [""],
    "dr.name": ["strong"],
    "dr.friction": [[1.25, 0.5], [-0.1, 1.0]],
    "dr.link_mass_scale": [[0.0, 1.2], [1.2, 0.9]],
    "dr.base_added_mass_kg": [[3.0, -1.0]],
    "dr.encoder_bias_rad": [[0.015, -0.015], [0.0]],
    "dr.base_com_offset_m": [[0.025, -0.05, 0.05], [0.025, 0.05]],
    "dr.effort_limit_scale": [[0.0, 1.1]],
    "dr.joint_damping_scale": [[-0.1, 1.0]],
    "dr.joint_friction": [[0.04, 0.0]],
    "dr.push_interval_s": [[0.0, 15.0], [15.0, 10.0]],
    "dr.push_lin_vel": [-1.0],
    "dr.push_ang_vel": [-0.4],
    "dr.control_delay_ms": [[-5.0, 20.0], [20.0, 0.0]],
    "dr.camera_pos_m": [-0.025],
    "dr.camera_rot_deg": [[2.5, -3.0, 2.5]],
    "dr.camera_fov_deg": [-2.0, 55.2, 60.0],  # must stay below depth.fovy (55.2)
    "terrain.size": [[0.0, 4.0], [1.9, 4.0], [3.5, 1.0], [3.5]],  # smoke: x must exceed 1.95
    "terrain.end_margin": [-0.25],
    "terrain.start_length": [0.0],
    "terrain.goal_length": [0.0],
    "terrain.platform_width": [0.0, 5.0],  # wider than the sub-terrain (4 m)
    "terrain.stone_size_easy": [[0.5, 0.45], [0.0, 0.5]],
    "terrain.stone_size_hard": [[-0.25, 0.3]],
    "terrain.gap_easy": [[0.15, 0.10], [-0.1, 0.1]],
    "terrain.gap_hard": [[0.45, 0.35]],
    "terrain.height_easy": [-0.01],
    "terrain.height_hard": [-0.1],
    "terrain.lateral_easy": [[0.1, 0.0]],
    "terrain.lateral_hard": [[-0.1, 0.21]],
    "terrain.pair_prob": [-0.1, 1.5],
    "terrain.pair_gap": [[0.2, 0.1]],
    "terrain.max_stones": [0],
    "terrain.pit_depth": [0.0],
    "terrain.hardware_stone_size": [[0.0, 0.3], [0.3]],
    "terrain.hardware_gaps": [[0.25, 0.3], [0.25, -0.3, 0.25, 0.3, 0.25]],
    "terrain.hardware_lateral": [[0.12, -0.12]],
}

# Keys with no domain beyond their type (OmegaConf refuses other types at composition).
FREE: dict[str, str] = {
    "eval.corruption": "a bool",
    "eval.randomization": "a bool",
    "eval.pushes": "a bool",
    "student.parts": "per-part blocks; each is checked by its part's own config (an unknown part is refused)",
    "reward.observe_reference": "a bool",
    "compute.compile_math": "a bool",
    "compute.replan_only_when_due": "a bool",
    "reward.label": "display text for the figures",
    "reward.color": "display only; analysis replaces an invalid or taken colour (noted)",
    "reward.order": "any int: legend position",
    "reward.tilt_limit_deg": "moved to termination.tilt_limit_deg (carried over, checked there)",
    "reward.min_base_height_m": "moved to termination.min_base_height_m (carried over)",
    "reward.max_foot_drop_m": "moved to termination.max_foot_drop_m (carried over)",
    "student.label": "display text for the figures",
    "student.color": "display only; analysis replaces an invalid or taken colour (noted)",
    "student.order": "any int: legend position",
}

# Values on the edge of their domain that must still be accepted.
GOOD: dict[str, list[Any]] = {
    "seed": [0, SEED_MAX],
    "curriculum.terrain_seed": [SEED_MAX],
    "reward.name": ["dense"],  # a new arm's name: a label (its terms define it)
    "student.variant": ["big"],  # a new variant's name: its parts are the composed ones
    "eval.terrain_seed": [1, SEED_MAX],
    "curriculum.promote_fraction": [1.0, 0.31],  # above demote_fraction (0.3)
    "curriculum.demote_fraction": [0.0, 0.99],
    "curriculum.max_init_level": [9],
    "teacher.gamma": [0.0, 1.0],
    "teacher.num_mini_batches": [32],
    "teacher.eval_interval": [0],
    "teacher.max_nonfinite_updates": [1],
    "reference.swing_toe_down": [-1.0, 0.0, 1.0],
    "reference.swing_height": [0.02, 0.3],
    "reference.swing_toe_roll": [-1.0, 0.0, 1.0],
    "reference.swing_xy_shape": [0.0, 0.5],
    "reference.swing_pitch_carry": [0.0, 1.0],
    "reference.swing_roll_out": [-0.5, 0.0, 0.5],
    "reference.swing_heel_strike": [0.0, 0.2, 0.5],
    "distill.max_nonfinite_updates": [1],
    "depth.width": [1],  # a 1x1-pixel camera still gives the CNN a 1x1 map
    "depth.height": [1],
    "depth.dropout": [0.0, 0.99],
    "depth.min_range": [0.0],
    "depth.delay_steps": [[0, 0], [3, 3]],
    "dr.friction": [[0.0, 0.0]],
    "dr.camera_fov_deg": [0.0, 55.0],
    "env.command_yaw_rate": [[0.0, 0.0]],
    "compute.device": ["cuda", "cuda:3"],  # CUDA's presence is checked before the run starts
    "compute.torch_threads": [0],
    "terrain.pair_prob": [0.0, 1.0],
    "terrain.size": [[1.96, 2.0]],  # 2 end_margin + start_length + the largest gap = 1.95
    "terrain.gap_easy": [[0.0, 0.0]],
    "student.init_log_std": [-3.0, 2.0],
    "student.cnn_kernels": [[4, 2, 3, 3]],  # even kernels: same padding still works
}


def leaves(cls: type = MarchConfig, prefix: str = "") -> dict[str, Any]:
    """Dotted key -> type hint of every leaf of the schema."""
    out: dict[str, Any] = {}
    hints = get_type_hints(cls)
    for f in fields(cls):
        hint = hints[f.name]
        if is_dataclass(hint):
            out.update(leaves(hint, f"{prefix}{f.name}."))
        else:
            out[f"{prefix}{f.name}"] = hint
    return out


SCHEMA = leaves()


@pytest.fixture(scope="module")
def base():
    return compose(["compute=smoke"])


def load_with(base, key: str, value: Any, *extra: tuple[str, Any]) -> MarchConfig:
    cfg = copy.deepcopy(base)
    for k, v in ((key, value), *extra):
        OmegaConf.update(cfg, k, v, merge=False)
    return to_march_config(cfg)


def assert_one_line_naming(err: ConfigError, key: str, value: Any) -> None:
    msg = str(err)
    assert "\n" not in msg, msg
    assert f"{key}=" in msg, f"{key!r} not named in: {msg}"
    for v in value if isinstance(value, (list, tuple)) else [value]:
        if isinstance(v, (int, float)):
            assert str(v) in msg or str(float(v)) in msg, f"value {v!r} not in: {msg}"


def test_every_schema_field_has_out_of_domain_cases():
    missing = sorted(set(SCHEMA) - set(BAD) - set(FREE))
    assert not missing, f"fields without out-of-domain cases (add to BAD or FREE): {missing}"
    stale = sorted((set(BAD) | set(FREE) | set(GOOD)) - set(SCHEMA))
    assert not stale, f"cases for keys the schema no longer has: {stale}"
    assert not set(BAD) & set(FREE)


def test_the_base_config_and_every_preset_are_accepted(base):
    to_march_config(base)
    for preset in ("cpu", "gpu", "smoke"):
        to_march_config(compose([f"compute={preset}"]))


CASES = [(k, v) for k, vs in BAD.items() for v in vs]


@pytest.mark.parametrize("key,value", CASES, ids=[f"{k}={v}" for k, v in CASES])
def test_out_of_domain_value_is_one_line_naming_key_and_value(base, key, value):
    with pytest.raises(ConfigError) as info:
        load_with(base, key, value)
    assert_one_line_naming(info.value, key, value)


GOOD_CASES = [(k, v) for k, vs in GOOD.items() for v in vs]


@pytest.mark.parametrize("key,value", GOOD_CASES, ids=[f"{k}={v}" for k, v in GOOD_CASES])
def test_boundary_value_is_accepted(base, key, value):
    cfg = load_with(base, key, value)
    section, _, name = key.rpartition(".")
    got = getattr(getattr(cfg, section) if section else cfg, name)
    assert list(got) == list(value) if isinstance(value, list) else got == value


def _float_leaves() -> list[str]:
    return [k for k, t in SCHEMA.items() if t is float]


def _fixed_tuples() -> list[tuple[str, int, Any]]:
    out = []
    for k, t in SCHEMA.items():
        args = get_args(t)
        if get_origin(t) is tuple and args and Ellipsis not in args:
            out.append((k, len(args), args[0]))
    return out


@pytest.mark.parametrize("key", _float_leaves())
@pytest.mark.parametrize("value", [NAN, INF, -INF])
def test_every_float_refuses_nan_and_inf(base, key, value):
    with pytest.raises(ConfigError) as info:
        load_with(base, key, value)
    msg = str(info.value)
    assert "\n" not in msg and f"{key}=" in msg and str(value) in msg, msg


@pytest.mark.parametrize("key,n,elem", _fixed_tuples(), ids=lambda x: str(x))
def test_every_fixed_size_tuple_refuses_another_length(base, key, n, elem):
    for length in (n - 1, n + 1):
        default = to_march_config(base)
        section, _, name = key.rpartition(".")
        value = list(getattr(getattr(default, section) if section else default, name))
        value = (value + value)[:length]
        with pytest.raises(ConfigError) as info:
            load_with(base, key, value)
        assert "\n" not in str(info.value) and f"{key}=" in str(info.value)


def test_float_tuples_refuse_nan(base):
    for key, _, elem in _fixed_tuples():
        if elem is not float:
            continue
        default = to_march_config(base)
        section, _, name = key.rpartition(".")
        value = list(getattr(getattr(default, section), name))
        value[-1] = NAN
        with pytest.raises(ConfigError, match=key.replace(".", r"\.") + "="):
            load_with(base, key, value)


@pytest.mark.parametrize(
    "extra,needle",
    [
        # Cross-field checks: each names the key whose value is out of the others' domain.
        ((("curriculum.promote_fraction", 0.5), ("curriculum.demote_fraction", 0.5)), "demote"),
        ((("eval.course", "hardware"),), "terrain.size=[3.5, 4.0]"),  # 4.8 m course, 3.5 m cell
        ((("compute.num_envs", 1), ("teacher.num_mini_batches", 9)), "num_mini_batches=9"),
        ((("depth.fovy", 1.5),), "dr.camera_fov_deg=2.0"),
        ((("student.log_std_max", -3.0),), "student.log_std_min=-3.0"),
        ((("curriculum.name", "flat_first"), ("curriculum.flat_levels", 0)), "flat_levels=0"),
        # Held-out evaluation courses: the eval seed may not be the training terrain's.
        ((("eval.terrain_seed", 0),), "eval.terrain_seed=0"),
    ],
)
def test_cross_field_domains(base, extra, needle):
    with pytest.raises(ConfigError) as info:
        load_with(base, *extra[0], *extra[1:])
    assert needle in str(info.value) and "\n" not in str(info.value), str(info.value)


def test_cnn_output_size_hand_derived():
    # 24x32 through kernels 5,3,3,3 / strides 1,2,2,1 with same padding: 24x32 -> 12x16 -> 6x8.
    assert cnn_output_hw((24, 32), (5, 3, 3, 3), (1, 2, 2, 1)) == (6, 8)
    assert cnn_output_hw((1, 1), (5, 3), (2, 2)) == (1, 1)
    # Even kernels: padding k // 2 adds a row, floor((7 + 4 - 4) / 2) + 1 = 4.
    assert cnn_output_hw((7, 7), (4,), (2,)) == (4, 4)
    assert cnn_output_hw((5, 9), (3, 3), (3, 3)) == (1, 1)


@pytest.mark.parametrize("case", range(24))
def test_cnn_output_size_matches_the_student_network(case):
    gen = torch.Generator().manual_seed(case)

    def draw(lo: int, hi: int) -> int:
        return int(torch.randint(lo, hi + 1, (1,), generator=gen))

    layers = draw(1, 4)
    kernels = tuple(draw(1, 6) for _ in range(layers))
    strides = tuple(draw(1, 3) for _ in range(layers))
    hw = (draw(1, 40), draw(1, 40))
    cfg = to_march_config(compose(["compute=smoke", "student=no_transformer"])).student
    cfg.cnn_channels, cfg.cnn_kernels, cfg.cnn_strides = (2,) * layers, kernels, strides
    cfg.fusion_mlp, cfg.head_hidden = (8,), (8,)
    net = StudentPolicy(
        cfg, proprio_dim=3, history_len=2, command_dim=2, image_hw=hw, num_actions=2
    )
    assert net.fmap_hw == cnn_output_hw(hw, kernels, strides)


def _train(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "march.train", "compute=smoke", *args, f"hydra.run.dir={tmp_path}"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )


@pytest.mark.parametrize(
    "override,needle",
    [
        ("seed=-1", "seed=-1 must be in [0, 2147483647]"),
        ("depth.width=0", "depth.width=0 must be >= 1"),
        ("curriculum.promote_fraction=2", "curriculum.promote_fraction=2.0 must be in (0, 1]"),
        ("resume=EMPTY", "not a march run directory"),
        ("terrain.pair_prob=1.5", "terrain.pair_prob=1.5 must be a probability in [0, 1]"),
    ],
)
def test_cli_bad_value_is_one_line_exit_2(tmp_path, override, needle):
    if override == "resume=EMPTY":
        (tmp_path / "empty").mkdir()
        override = f"resume={tmp_path / 'empty'}"
    out = _train(tmp_path / "run", override)
    lines = out.stderr.strip().splitlines()
    assert out.returncode == 2, out.stderr[-2000:]
    assert len(lines) == 1 and lines[0].startswith("error: ") and needle in lines[0], lines
    assert "Traceback" not in out.stdout + out.stderr
    assert not (tmp_path / "run" / "teacher").exists()  # nothing started
    assert not (tmp_path / "run").exists()  # and no run directory is left behind


def test_resume_of_a_run_directory_with_only_its_config_is_accepted(tmp_path):
    """A run killed before its first checkpoint holds config.yaml: resume starts it again."""
    from march.train import _check_inputs

    run = tmp_path / "run"
    run.mkdir()
    cfg = to_march_config(compose(["compute=smoke", f"resume={run}"]))
    with pytest.raises(ConfigError, match="not a march run directory"):
        _check_inputs(cfg)
    (run / "config.yaml").write_text("seed: 0\n")
    _check_inputs(cfg)
    (run / "config.yaml").unlink()
    (run / "teacher").mkdir()
    (run / "teacher" / "model_000001.pt").write_bytes(b"")
    _check_inputs(cfg)


def test_finite_check_covers_dict_values(base):
    terms = dict(to_march_config(base).reward.terms)
    key = next(iter(terms))
    terms[key] = NAN
    with pytest.raises(ConfigError, match=r"reward\.terms="):
        load_with(base, "reward.terms", terms)
