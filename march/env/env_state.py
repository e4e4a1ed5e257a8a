"""The env's part of a run's training state: what a resume must give back besides the networks.

A checkpoint cannot hold the physics (every env restarts its episode on resume), but it holds
what the next iteration depends on beyond the episode's own motion:

- ``curriculum``: every env's terrain level and column (``terrain_levels``, ``terrain_types``)
  and the number of levels; the spawn origins follow from them;
- ``episode``: every env's episode clock (``episode_length_buf``: time-outs keep their schedule)
  and the tensors of the command terms other than ``reference`` (the twist command each env
  walks to and its resampling clock); the reference is planned afresh from the reset robot;
- the planner's generator (the ``reference`` term's ``torch.Generator``), for the random streams
  of :mod:`march.learn.train_state`;
- ``planner``: the counters of the planner's per-env streams (``planner_streams``, keyed by
  (seed, env): issue 55), so the resumed envs' plans draw where the saved run would have.

:func:`restore_env_state` puts levels back and resets every env while ``common_step_counter``
is still 0 (the curriculum term moves no level on that reset), so the resumed envs start from
exactly the saved levels.
"""

from __future__ import annotations

import hashlib
from typing import TYPE_CHECKING, Any

import torch

from march.env.rewards import REFERENCE_COMMAND

if TYPE_CHECKING:
    from mjlab.envs import ManagerBasedRlEnv


class EnvStateError(ValueError):
    """A saved env state that does not fit this env (the runner reports it as one line)."""


def _terrain(env: ManagerBasedRlEnv) -> Any:
    terrain = env.scene.terrain
    return terrain if getattr(terrain, "terrain_levels", None) is not None else None


def mean_terrain_level(env: ManagerBasedRlEnv) -> float:
    """The mean terrain level over the envs (NaN without a level curriculum); syncs once."""
    terrain = _terrain(env)
    return float(terrain.terrain_levels.float().mean()) if terrain is not None else float("nan")


def levels_digest(levels: torch.Tensor) -> str:
    """A short digest of per-env levels (what a resume prints, what the kill trials compare)."""
    data = levels.detach().to("cpu", torch.int64).contiguous().numpy().tobytes()
    return hashlib.sha1(data).hexdigest()[:12]


def planner_generator(env: ManagerBasedRlEnv) -> torch.Generator | None:
    """The reference command's planner generator, if the env plans footsteps."""
    if REFERENCE_COMMAND not in env.command_manager.active_terms:
        return None
    return env.command_manager.get_term(REFERENCE_COMMAND).generator


def _command_tensors(term: Any, num_envs: int) -> dict[str, torch.Tensor]:
    return {
        k: v
        for k, v in vars(term).items()
        if isinstance(v, torch.Tensor) and v.dim() >= 1 and v.shape[0] == num_envs
    }


def env_state(env: ManagerBasedRlEnv) -> dict[str, Any]:
    """``curriculum`` and ``episode`` entries of a checkpoint (plain data, CPU tensors)."""
    out: dict[str, Any] = {}
    terrain = _terrain(env)
    if terrain is not None:
        out["curriculum"] = {
            "terrain_levels": terrain.terrain_levels.detach().cpu().clone(),
            "terrain_types": terrain.terrain_types.detach().cpu().clone(),
            "max_terrain_level": int(terrain.max_terrain_level),
        }
    commands = {
        name: {k: v.detach().cpu().clone() for k, v in _command_tensors(term, env.num_envs).items()}
        for name in env.command_manager.active_terms
        if name != REFERENCE_COMMAND
        for term in [env.command_manager.get_term(name)]
    }
    out["episode"] = {
        "episode_length_buf": env.episode_length_buf.detach().cpu().clone(),
        "commands": commands,
    }
    streams = _planner_streams(env)
    if streams is not None:
        out["planner"] = {"stream_counts": streams.counts.detach().cpu().clone()}
    return out


def _planner_streams(env: ManagerBasedRlEnv) -> Any:
    """The reference command's per-env planner streams, if the env plans footsteps."""
    if REFERENCE_COMMAND not in env.command_manager.active_terms:
        return None
    return getattr(env.command_manager.get_term(REFERENCE_COMMAND), "planner_streams", None)


def _tensor(state: dict[str, Any], key: str, where: str, num_envs: int) -> torch.Tensor:
    value = state.get(key)
    if not isinstance(value, torch.Tensor) or value.dim() < 1 or value.shape[0] != num_envs:
        shape = tuple(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__
        raise EnvStateError(f"'{where}.{key}' is {shape}, not a tensor over the {num_envs} envs")
    return value


def restore_env_state(env: ManagerBasedRlEnv, payload: dict[str, Any]) -> list[str]:
    """Put back a checkpoint's ``curriculum`` and ``episode`` entries; one line per thing a
    checkpoint lacked. Call it on a freshly built env (``common_step_counter`` 0), before the
    random streams are restored (the reset here draws from them)."""
    notes: list[str] = []
    n = env.num_envs
    terrain = _terrain(env)
    cur = payload.get("curriculum")
    if terrain is not None and isinstance(cur, dict):
        levels = _tensor(cur, "terrain_levels", "curriculum", n)
        types = _tensor(cur, "terrain_types", "curriculum", n)
        rows, cols = terrain.terrain_origins.shape[:2]
        if int(cur.get("max_terrain_level", rows)) != int(terrain.max_terrain_level) or not (
            0 <= int(levels.min())
            and int(levels.max()) < rows
            and 0 <= int(types.min())
            and int(types.max()) < cols
        ):
            raise EnvStateError(
                f"'curriculum' holds levels outside this terrain's {rows} x {cols} courses"
            )
        dev = terrain.terrain_levels.device
        terrain.terrain_levels[:] = levels.to(dev, terrain.terrain_levels.dtype)
        terrain.terrain_types[:] = types.to(dev, terrain.terrain_types.dtype)
        terrain.env_origins[:] = terrain.terrain_origins[
            terrain.terrain_levels, terrain.terrain_types
        ]
    elif terrain is not None:
        notes.append("the checkpoint holds no terrain levels (an older run): levels start over")
    # Every env restarts its episode from its restored cell; on this reset (the step counter is
    # still 0) the curriculum term moves no level.
    counter, env.common_step_counter = env.common_step_counter, 0
    env.reset()
    env.common_step_counter = counter
    episode = payload.get("episode")
    if isinstance(episode, dict):
        buf = _tensor(episode, "episode_length_buf", "episode", n)
        env.episode_length_buf[:] = buf.to(env.episode_length_buf.device)
        for name, saved in (episode.get("commands") or {}).items():
            if name not in env.command_manager.active_terms or not isinstance(saved, dict):
                continue
            current = _command_tensors(env.command_manager.get_term(name), n)
            for key, value in saved.items():
                if key in current and isinstance(value, torch.Tensor):
                    if value.shape != current[key].shape:
                        raise EnvStateError(
                            f"'episode.commands.{name}.{key}' is {tuple(value.shape)}, "
                            f"the env's is {tuple(current[key].shape)}"
                        )
                    current[key].copy_(value.to(current[key].device, current[key].dtype))
    else:
        notes.append("the checkpoint holds no episode clocks (an older run): episodes start over")
    streams, planner = _planner_streams(env), payload.get("planner")
    if streams is not None and isinstance(planner, dict):
        counts = _tensor(planner, "stream_counts", "planner", n)
        streams.counts.copy_(counts.to(streams.counts.device, streams.counts.dtype))
    elif streams is not None:
        notes.append("the checkpoint holds no planner stream counters (an older run): they restart")
    return notes
