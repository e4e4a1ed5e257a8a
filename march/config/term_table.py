"""march's own reward terms as data: what checking a config needs of each (its parameters, which
are required, the defaults it registers, what it needs from the env), without importing the
simulator. Generated from the registry (``march.config.terms.table_entry`` of every term
``march.env.rewards`` registers); ``tests/test_config_terms.py`` compares it with the registry
and prints the new table when a term changes."""

from __future__ import annotations

from typing import Any

BUILTIN_TERMS: dict[str, dict[str, Any]] = {
    "action_rate": {
        "origin": "mjlab.envs.mdp.rewards.penalty_action_rate_l2",
        "parameters": [],
        "required": [],
        "registered": [],
        "needs": [],
        "takes_any": False,
        "doc": "Penalize the rate of change of the actions using L2 squared kernel.",
    },
    "alive": {
        "origin": "march.env.rewards.alive",
        "parameters": [],
        "required": [],
        "registered": [],
        "needs": [],
        "takes_any": False,
        "doc": "1 per control step while the episode runs (one kept tensor: the reward "
        "manager only",
    },
    "body_ang_vel": {
        "origin": "mjlab.tasks.velocity.mdp.rewards.penalty_body_angular_velocity_penalty",
        "parameters": ["asset_cfg"],
        "required": [],
        "registered": ["asset_cfg"],
        "needs": [],
        "takes_any": False,
        "doc": "Penalize excessive body angular velocities.",
    },
    "clf": {
        "origin": "march.env.rewards.clf",
        "parameters": ["command_name"],
        "required": [],
        "registered": [],
        "needs": ["reference"],
        "takes_any": False,
        "doc": "r_clf = exp(-min(V, Vmax)/Vmax) in [e^-1, 1] (V computed once per step by the "
        "command).",
    },
    "dclf": {
        "origin": "march.env.rewards.dclf",
        "parameters": ["command_name"],
        "required": [],
        "registered": [],
        "needs": ["reference"],
        "takes_any": False,
        "doc": "r_dclf = -max((dV/dt + alpha V)/Vdmax, 0) <= 0; 0 where V has no history yet "
        "(episode",
    },
    "feet_edge_distance": {
        "origin": "march.env.rewards.feet_edge_distance",
        "parameters": ["clearance", "sensor_name"],
        "required": [],
        "registered": [],
        "needs": [],
        "takes_any": False,
        "doc": "Foothold safety (model-free set), in [-2, 0]: for each foot touching the terrain,",
    },
    "foot_slip": {
        "origin": "march.env.rewards.foot_slip",
        "parameters": ["sensor_name", "command_name", "command_threshold", "site_names"],
        "required": [],
        "registered": ["command_name", "command_threshold", "sensor_name", "site_names"],
        "needs": [],
        "takes_any": False,
        "doc": "-(mjlab's ``feet_slip``): sum over feet in contact of |v_xy|^2 while "
        "the command is",
    },
    "forward_progress": {
        "origin": "march.env.rewards.forward_progress",
        "parameters": ["command_name"],
        "required": [],
        "registered": ["command_name"],
        "needs": [],
        "takes_any": False,
        "doc": "Velocity along the commanded direction, capped at the command (rewards crossing).",
    },
    "holonomic_pos": {
        "origin": "march.env.rewards.holonomic_pos",
        "parameters": ["sigma", "command_name"],
        "required": [],
        "registered": [],
        "needs": ["reference"],
        "takes_any": False,
        "doc": "exp(-||p - p_td||^2 / sigma^2) in (0, 1]: stance foot site "
        "displacement from where it",
    },
    "holonomic_vel": {
        "origin": "march.env.rewards.holonomic_vel",
        "parameters": ["sigma", "command_name"],
        "required": [],
        "registered": [],
        "needs": ["reference"],
        "takes_any": False,
        "doc": "exp(-(||v||^2 + w_z^2) / sigma^2) in (0, 1]: stance foot site "
        "linear velocity and yaw",
    },
    "joint_limits": {
        "origin": "mjlab.envs.mdp.rewards.penalty_joint_pos_limits",
        "parameters": ["asset_cfg"],
        "required": [],
        "registered": [],
        "needs": [],
        "takes_any": False,
        "doc": "Penalize joint positions if they cross the soft limits.",
    },
    "torque": {
        "origin": "march.env.rewards.torque_l2",
        "parameters": [],
        "required": [],
        "registered": [],
        "needs": [],
        "takes_any": False,
        "doc": "Sum of squared actuator forces [N^2 m^2] (returned <= 0).",
    },
    "track_angular_velocity": {
        "origin": "mjlab.tasks.velocity.mdp.rewards.track_angular_velocity",
        "parameters": ["std", "command_name", "asset_cfg"],
        "required": [],
        "registered": ["command_name", "std"],
        "needs": [],
        "takes_any": False,
        "doc": "Reward heading error for heading-controlled envs, angular velocity for others.",
    },
    "track_linear_velocity": {
        "origin": "mjlab.tasks.velocity.mdp.rewards.track_linear_velocity",
        "parameters": ["std", "command_name", "asset_cfg"],
        "required": [],
        "registered": ["command_name", "std"],
        "needs": [],
        "takes_any": False,
        "doc": "Reward for tracking the commanded base linear velocity.",
    },
    "upright": {
        "origin": "march.env.rewards.upright",
        "parameters": ["std", "body_names"],
        "required": [],
        "registered": ["body_names", "std"],
        "needs": [],
        "takes_any": False,
        "doc": "mjlab's ``upright`` kernel exp(-|g_xy|^2 / std^2) of the body's projected "
        "gravity (flat",
    },
}
"""Term name -> its table entry (march.config.terms.from_table makes a spec of one)."""
