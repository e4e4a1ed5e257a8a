"""An evaluation env's random numbers keyed by rollout index, whatever the waves and ranks.

mjlab and march draw an env's randomness (reset pose, domain randomisation, observation noise,
observation delays, pushes, the command, the depth corruption, the planner's samples) from torch's
one generator, a batch at a time: what a rollout sees would depend on how many envs share its
wave and where it sits. Inside :func:`keyed_draws`, every draw is taken instead from
:class:`march.keyed_random.RowStreams`, one stream per env row keyed by (evaluation seed, the
rollout the row runs), so an evaluation's rows are the same in 1 wave, in 4 waves or over 2 ranks
(tests/test_distributed.py, tests/test_rollout_draws.py).

How a draw finds its rows: the draws of mjlab's and march's terms have the batch first
(``(n, ...)``). Inside ``env._reset_idx(env_ids)`` a draw of ``len(env_ids)`` rows is those envs';
anywhere, a draw of ``num_envs`` rows is every env's. The planner's samples are per env row and
advance only the rows it applies (:meth:`KeyedDraws.planner_uniform`). A draw of any other shape,
or through a torch sampler with no keyed form (``randperm``, ``multinomial``, ...), is refused
with one line naming its caller: a term that draws so would make the rows depend on the waves
again, so it is an error rather than a silent difference.

At each wave (:meth:`KeyedDraws.start_wave`) the rows are keyed by their rollouts, counters start
at 0, every randomised model field is put back at the compiled model's value and mjlab's
``startup`` events (the link masses, the added base mass, the CoM offset: drawn once at build,
per env slot) are applied again, now per rollout.

torch's functions are swapped for the keyed ones only inside the context and restored on exit
(also on an exception); the evaluation runs on one thread. Plain tensor ops: no host read.
"""

from __future__ import annotations

import contextlib
import traceback
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from march.keyed_random import RowStreams

if TYPE_CHECKING:
    from mjlab.envs import ManagerBasedRlEnv

KEYED_SAMPLERS = (
    "rand", "randn", "randint", "rand_like", "randn_like", "randint_like", "normal", "bernoulli"
)  # fmt: skip
"""torch functions with a keyed form inside :func:`keyed_draws`."""
KEYED_METHODS = ("uniform_", "normal_")
"""Tensor methods with a keyed form."""
REFUSED_SAMPLERS = ("randperm", "multinomial", "poisson")
REFUSED_METHODS = ("random_", "bernoulli_", "exponential_", "geometric_", "log_normal_", "cauchy_")
"""torch samplers without a keyed form: refused inside :func:`keyed_draws`."""


class UnkeyedDrawError(RuntimeError):
    """A random draw inside an evaluation that cannot be keyed by rollout."""


def _caller() -> str:
    """The first frame outside torch and this module, as ``path:line in function``."""
    here = Path(__file__).resolve()
    for frame in reversed(traceback.extract_stack()[:-2]):
        path = Path(frame.filename)
        if path.resolve() != here and "torch" not in path.parts:
            return f"{frame.filename}:{frame.lineno} in {frame.name}"
    return "unknown caller"


def _shape(size: tuple[Any, ...]) -> tuple[int, ...]:
    """torch's ``*size`` convention: ints, or one tuple / list / torch.Size."""
    if len(size) == 1 and isinstance(size[0], (tuple, list, torch.Size)):
        size = tuple(size[0])
    return tuple(int(s) for s in size)


class KeyedDraws:
    """The keyed streams of one eval env and the row scope of its current draw."""

    def __init__(self, env: ManagerBasedRlEnv, seed: int) -> None:
        self.env = env
        self.seed = int(seed)
        self.num_envs = int(env.num_envs)
        self.streams = RowStreams(self.num_envs, env.device)
        self.scope: torch.Tensor | None = None
        """The env ids of the reset in progress (``env._reset_idx``), or None."""

    def start_wave(self, first_rollout: int) -> None:
        """Row ``b`` runs rollout ``first_rollout + b``: rekey, restart the counters and apply
        mjlab's ``startup`` events again (module docstring)."""
        self.streams.assign(self.seed, first_rollout)
        manager = self.env.event_manager
        restore_randomized_fields(self.env)
        if "startup" in manager.available_modes:
            manager.apply(mode="startup")
        # (The reference term keys its body-mass cache on the model's mass tensor and its
        # version, so the masses written here are read again without a reset from outside.)

    def rows(self, n: int, what: str) -> torch.Tensor | None:
        """The env rows of a draw of ``n`` rows (None: all of them), or one clear error."""
        if self.scope is not None and n == self.scope.numel():
            return self.scope
        if n == self.num_envs:
            return None
        raise UnkeyedDrawError(
            f"evaluation: {what} of {n} rows drawn at {_caller()}: a draw in the evaluation env "
            f"must have the env batch first ({self.num_envs} envs, or the envs being reset) to "
            "be keyed by rollout (march.env.rollout_draws)"
        )

    def uniform(self, shape: tuple[int, ...], dtype: torch.dtype | None, what: str) -> torch.Tensor:
        if not shape:
            self.rows(1, what)  # a scalar draw: never one env's
        rows = self.rows(shape[0], what)
        return self.streams.uniform(rows, shape[1:], dtype or torch.get_default_dtype())

    def normal(self, shape: tuple[int, ...], dtype: torch.dtype | None, what: str) -> torch.Tensor:
        if not shape:
            self.rows(1, what)
        rows = self.rows(shape[0], what)
        return self.streams.normal(rows, shape[1:], dtype or torch.get_default_dtype())

    def integers(
        self, low: int, high: int, shape: tuple[int, ...], dtype: torch.dtype | None, what: str
    ) -> torch.Tensor:
        if not shape:
            self.rows(1, what)
        rows = self.rows(shape[0], what)
        return self.streams.integers(rows, low, high, shape[1:], dtype or torch.int64)

    def planner_uniform(
        self, env_ids: torch.Tensor, apply: torch.Tensor
    ) -> Callable[[tuple[int, ...]], torch.Tensor]:
        """The planner's per-row uniforms for the batch ``env_ids`` (n,): a draw advances the rows
        whose plan is applied only (``apply`` (n,) bool; padding rows are planned and discarded,
        march.env.replan_queue), so an env's samples never depend on the others' touchdowns."""
        ids = env_ids.long()

        def draw(shape: tuple[int, ...]) -> torch.Tensor:
            return self.streams.uniform(ids, shape, torch.float32, advance=apply)

        return draw


def restore_randomized_fields(env: ManagerBasedRlEnv) -> None:
    """Every model field an event term randomises (``model_fields`` of mjlab's
    ``requires_model_fields``) back at the compiled model's value in every world. A term that
    keeps part of the current value (march.env.dr_terms keeps the mass added on top of the
    scaled one) would otherwise carry the previous wave's draw in its last bits."""
    from mjlab.managers.event_manager import _DERIVED_FIELDS  # recomputed after the events

    manager = env.event_manager
    for cfgs in manager._mode_term_cfgs.values():
        for term_cfg in cfgs:
            derived = _DERIVED_FIELDS.get(getattr(term_cfg.func, "recompute", None), ())
            for field in getattr(term_cfg.func, "model_fields", ()):
                if field in derived:
                    continue
                try:
                    current = getattr(env.sim.model, field)
                except TypeError:  # a vector-typed field (the force ranges): mjlab's own terms
                    continue  # write those from the defaults, never from the current value
                current.copy_(env.sim.get_default_field(field).expand_as(current))


def _patched(draws: KeyedDraws) -> dict[tuple[Any, str], Callable]:
    """The keyed (and refusing) replacements of torch's samplers, by (owner, name)."""

    def on_device(x: torch.Tensor, device: Any, out: torch.Tensor | None = None) -> torch.Tensor:
        x = x if device is None else x.to(device)
        return x if out is None else out.copy_(x)

    def rand(*size, dtype=None, device=None, out=None, **_):
        return on_device(draws.uniform(_shape(size), dtype, "torch.rand"), device, out)

    def randn(*size, dtype=None, device=None, out=None, **_):
        return on_device(draws.normal(_shape(size), dtype, "torch.randn"), device, out)

    def randint(*args, size=None, low=None, high=None, dtype=None, device=None, out=None, **_):
        ints = [a for a in args if not isinstance(a, (tuple, list, torch.Size))]
        sizes = [a for a in args if isinstance(a, (tuple, list, torch.Size))]
        shape = _shape((size if size is not None else sizes[0],))
        if high is None:
            low, high = (0, ints[0]) if len(ints) == 1 else (low or ints[0], ints[-1])
        low = 0 if low is None else low
        x = draws.integers(int(low), int(high), shape, dtype, "torch.randint")
        return on_device(x, device, out)

    def rand_like(x, dtype=None, device=None, **_):
        return on_device(
            draws.uniform(tuple(x.shape), dtype or x.dtype, "torch.rand_like"), device or x.device
        )

    def randn_like(x, dtype=None, device=None, **_):
        return on_device(
            draws.normal(tuple(x.shape), dtype or x.dtype, "torch.randn_like"), device or x.device
        )

    def randint_like(x, *args, dtype=None, device=None, **_):
        low, high = (0, args[0]) if len(args) == 1 else args
        out = draws.integers(
            int(low), int(high), tuple(x.shape), dtype or x.dtype, "torch.randint_like"
        )
        return on_device(out, device or x.device)

    def normal(mean, std=1.0, *args, out=None, **_):
        """torch.normal(mean, std) with a tensor mean or std (torch.distributions.Normal's
        sample); the (float, float, size) form has no batch to key and is refused."""
        if not isinstance(mean, torch.Tensor) and not isinstance(std, torch.Tensor):
            refuse("torch.normal(float, float, size)")()
        shape = torch.broadcast_shapes(
            *(t.shape for t in (mean, std) if isinstance(t, torch.Tensor))
        )
        like = mean if isinstance(mean, torch.Tensor) else std
        z = draws.normal(tuple(shape), like.dtype, "torch.normal").to(like.device)
        return on_device(z * std + mean, None, out)

    def bernoulli(p, *args, out=None, **_):
        u = draws.uniform(tuple(p.shape), p.dtype, "torch.bernoulli").to(p.device)
        return on_device((u < p).to(p.dtype), None, out)

    def uniform_(self, a=0.0, b=1.0, *, generator=None, **kw):
        a, b = kw.get("from", a), kw.get("to", b)
        u = draws.uniform(tuple(self.shape), self.dtype, "Tensor.uniform_")
        return self.copy_(u * (b - a) + a)

    def normal_(self, mean=0.0, std=1.0, *, generator=None):
        z = draws.normal(tuple(self.shape), self.dtype, "Tensor.normal_")
        return self.copy_(z * std + mean)

    def refuse(name: str) -> Callable:
        def refused(*_, **__):
            raise UnkeyedDrawError(
                f"evaluation: {name} at {_caller()} has no form keyed by rollout "
                "(march.env.rollout_draws): draw with torch.rand / randn / randint, batch first"
            )

        return refused

    table: dict[tuple[Any, str], Callable] = {
        (torch, "rand"): rand,
        (torch, "randn"): randn,
        (torch, "randint"): randint,
        (torch, "rand_like"): rand_like,
        (torch, "randn_like"): randn_like,
        (torch, "randint_like"): randint_like,
        (torch, "normal"): normal,
        (torch, "bernoulli"): bernoulli,
        (torch.Tensor, "uniform_"): uniform_,
        (torch.Tensor, "normal_"): normal_,
    }
    for name in REFUSED_SAMPLERS:
        table[(torch, name)] = refuse(f"torch.{name}")
    for name in REFUSED_METHODS:
        table[(torch.Tensor, name)] = refuse(f"Tensor.{name}")
    return table


@contextlib.contextmanager
def keyed_draws(env: ManagerBasedRlEnv, seed: int) -> Iterator[KeyedDraws]:
    """Inside: every random draw of ``env`` keyed by rollout (module docstring); the caller
    calls :meth:`KeyedDraws.start_wave` before each wave's reset."""
    draws = KeyedDraws(env, seed)
    table = _patched(draws)
    saved = {key: getattr(*key) for key in table}
    reset_idx = env._reset_idx  # the bound method mjlab's reset and step call

    def scoped_reset(env_ids: torch.Tensor | None = None) -> None:
        draws.scope = None if env_ids is None else env_ids.long()
        try:
            reset_idx(env_ids)
        finally:
            draws.scope = None

    try:
        for (owner, name), fn in table.items():
            setattr(owner, name, fn)
        env._reset_idx = scoped_reset  # type: ignore[method-assign]
        env.rollout_draws = draws  # type: ignore[attr-defined]
        yield draws
    finally:
        for (owner, name), fn in saved.items():
            setattr(owner, name, fn)
        env.__dict__.pop("_reset_idx", None)
        env.__dict__.pop("rollout_draws", None)


def active(env: Any) -> KeyedDraws | None:
    """The env's keyed draws while an evaluation runs (:func:`keyed_draws`), else None."""
    return getattr(env, "rollout_draws", None)
