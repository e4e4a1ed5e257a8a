"""Per-env constants and per-compute sharing for march's mjlab terms (issue 11: a lean step).

Two kinds of reuse, both keyed on the env object (one built env = one cache):

- :func:`constant`: something fixed once the env is built (site ids found by regex, index
  tensors, a ones vector) is computed on first use and kept, instead of every step.
- :func:`shared`: a value that several terms of *one* manager ``compute`` need (the actor and the
  critic group both observe the stones ahead and the reference; two holonomic rewards read the
  stance foot) is computed once per ``compute`` call. The first call of :func:`shared` on an env
  wraps that env's observation and reward managers' ``compute`` so that a fresh cache exists
  while one runs; outside a manager's ``compute`` (tests, tools calling a term directly, the
  manager's own shape probe at build time) nothing is cached and the value is computed afresh,
  so a cached value can never outlive the state it was computed from.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable
from typing import Any, TypeVar

T = TypeVar("T")

_CONSTANTS = "_march_constants"
_SHARED = "_march_shared"
_WRAPPED = "_march_shared_wrapped"
MANAGERS = ("observation_manager", "reward_manager")
"""The managers whose ``compute`` scopes a shared cache."""


def constant(env: Any, key: Hashable, make: Callable[[], T]) -> T:
    """``make()`` the first time ``key`` is asked for on ``env``, the kept value afterwards."""
    store = env.__dict__.setdefault(_CONSTANTS, {})
    if key not in store:
        store[key] = make()
    return store[key]


def _scope(env: Any, compute: Callable[..., Any]) -> Callable[..., Any]:
    def scoped(*args: Any, **kwargs: Any) -> Any:
        outer = env.__dict__.get(_SHARED)
        env.__dict__[_SHARED] = {}
        try:
            return compute(*args, **kwargs)
        finally:
            env.__dict__[_SHARED] = outer

    return scoped


def install(env: Any) -> None:
    """Wrap the env's observation and reward managers' ``compute`` (once; idempotent). Managers
    not built yet (a term called while its manager is being constructed) are wrapped later."""
    for attr in MANAGERS:
        manager = env.__dict__.get(attr)
        if manager is None or getattr(manager, _WRAPPED, False):
            continue
        manager.compute = _scope(env, manager.compute)
        setattr(manager, _WRAPPED, True)


def shared(env: Any, key: Hashable, make: Callable[[], T]) -> T:
    """``make()`` once per observation / reward manager ``compute`` (module docstring)."""
    cache = env.__dict__.get(_SHARED)
    if cache is None:
        install(env)
        return make()
    if key not in cache:
        cache[key] = make()
    return cache[key]


def _site_frames(env: Any, names: tuple[str, ...], entity: str) -> tuple[Any, Any, int]:
    """(global site ids, their bodies' ids, the entity's root body id), kept."""
    import torch

    def make() -> tuple[torch.Tensor, torch.Tensor, int]:
        ent = env.scene[entity]
        local, _ = ent.find_sites(names, preserve_order=True)
        idx = torch.as_tensor(local, dtype=torch.long, device=ent.indexing.site_ids.device)
        gid = ent.indexing.site_ids[idx].to(env.device, torch.long)
        body = ent.data.model.site_bodyid[gid].to(env.device, torch.long)
        return gid, body, int(ent.indexing.root_body_id)

    return constant(env, ("site_frames", entity, tuple(names)), make)


def site_pos(env: Any, names: tuple[str, ...], entity: str = "robot") -> Any:
    """(E, n, 3) world positions of the sites ``names`` of ``entity``: mjlab's
    ``data.site_pos_w[:, ids]`` without its pose of every site (a matrix-to-quaternion
    conversion of all of them per call)."""
    gid, _, _ = _site_frames(env, names, entity)
    return env.scene[entity].data.data.site_xpos[:, gid]


def site_state(env: Any, names: tuple[str, ...], entity: str = "robot") -> tuple[Any, Any, Any]:
    """World position, linear and angular velocity, each (E, n, 3), of the sites ``names``:
    mjlab's ``site_pos_w`` / ``site_lin_vel_w`` / ``site_ang_vel_w`` (velocity from the body's
    ``cvel`` about the root subtree CoM) for these sites only. Once per manager compute
    (:func:`shared`): the measured CLF outputs and the holonomic rewards read the same feet."""
    return shared(env, ("site_state", names, entity), lambda: _site_state(env, names, entity))


def _site_state(env: Any, names: tuple[str, ...], entity: str) -> tuple[Any, Any, Any]:
    import torch

    gid, body, root = _site_frames(env, names, entity)
    data = env.scene[entity].data.data
    pos = data.site_xpos[:, gid]
    cvel = data.cvel[:, body]
    ang = cvel[..., 0:3]
    offset = data.subtree_com[:, root].unsqueeze(1) - pos
    lin = cvel[..., 3:6] - torch.cross(ang, offset, dim=-1)
    return pos, lin, ang


def site_xmat(env: Any, names: tuple[str, ...], entity: str = "robot") -> Any:
    """(E, n, 3, 3) world rotation matrices of the sites ``names`` (MuJoCo's ``site_xmat``)."""
    gid, _, _ = _site_frames(env, names, entity)
    xmat = env.scene[entity].data.data.site_xmat[:, gid]
    return xmat.reshape(xmat.shape[0], gid.shape[0], 3, 3)


def root_frame(env: Any, entity: str = "robot") -> tuple[Any, Any]:
    """The root link's world position (E, 3) and heading (E,) [rad], once per manager compute:
    mjlab's ``root_link_pos_w`` (a view of MuJoCo's ``xpos``, not the pose ``cat`` it slices)
    and ``heading_w`` read from the root's rotation matrix, atan2(R10, R00) (the world x-y
    direction of the body's x axis, which mjlab rotates out of the quaternion: ~7 ops a call)."""

    def make() -> tuple[Any, Any]:
        import torch

        ent = env.scene[entity]
        root = int(ent.indexing.root_body_id)
        data = ent.data.data
        mat = data.xmat[:, root].reshape(-1, 3, 3)
        return data.xpos[:, root], torch.atan2(mat[:, 1, 0], mat[:, 0, 0])

    return shared(env, ("root_frame", entity), make)
