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


def site_ids(env: Any, names: tuple[str, ...], entity: str = "robot") -> Any:
    """(len(names),) long tensor of the sites ``names`` of ``entity``, in the given order, on the
    env's device (``find_sites`` runs once)."""
    import torch

    def make() -> torch.Tensor:
        ids, _ = env.scene[entity].find_sites(names, preserve_order=True)
        return torch.tensor(ids, dtype=torch.long, device=env.device)

    return constant(env, ("site_ids", entity, tuple(names)), make)
