"""The one door to a checkpoint: every tool reads one here, with the same checks and messages.

``march.train`` (``teacher_ckpt=`` / ``student_ckpt=``, a resume's and a run directory's own
checkpoints), ``march.play`` and ``march.export`` call :func:`read_checkpoint` or
:func:`policy_from_checkpoint`; nothing else in march opens a checkpoint. In this order, each
fault one :class:`~march.config.ConfigError` line naming the file, before any env is built:

1. the file (:func:`march.store.checkpoint.load_checkpoint`): no symbolic link, a regular file
   within :data:`~march.store.checkpoint.MAX_CHECKPOINT_BYTES`, plain data only (weights-only
   unpickling: nothing in it runs), the right kind;
2. its entries (:func:`check_checkpoint`): iteration and env steps whole numbers in range, no
   ``${...}`` interpolation or resolver anywhere in its config, the config valid as if typed on
   the command line (types, ranges, the memory bound);
3. the modules its config names (:func:`~march.store.file_config.check_named_modules`): imported only when the user names
   them too (``extra_modules=[...]`` on the command line or in their config);
4. its weights against its config (:func:`check_weights`): every tensor's shape that the network
   its config and layout describe would have, built on the ``meta`` device (no memory).

Then :func:`policy_from_checkpoint` takes the policy-defining fields from the checkpoint's
config (:mod:`march.store.provenance`). The rules comparing a run's saved config with a new one
are :mod:`march.store.resume_rules`; the run directory's lock, links and files are
:mod:`march.store.run_dir`.
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Sequence
from typing import Any

import torch

from march.config import ConfigError, MarchConfig, to_march_config
from march.store.checkpoint import CheckpointError, load_checkpoint
from march.store.checkpoint_file import check_checkpoint_files
from march.store.file_config import check_named_modules, interpolations
from march.store.provenance import apply_checkpoint_config, policy_changes

ITERATION_MAX = 10**9
"""No march stage runs anywhere near this many iterations: a larger count is not a checkpoint's."""


def check_checkpoint(
    payload: dict[str, Any], kind: str, label: str, named: Sequence[str] | None = None
) -> MarchConfig | None:
    """A checkpoint's config, iteration and env-step count through the command line's checks:
    types and ranges, no interpolation or resolver, the modules it names named by the user
    (``named``: the user's ``extra_modules``; None: the check was made by the caller), the
    config's own checks and the memory bound. Returns the checkpoint's config (None when it has
    none: an older checkpoint). Raises :class:`ConfigError` naming the file (``label``)."""
    from omegaconf import OmegaConf

    from march.config.memory import check_memory

    def refuse(what: str) -> ConfigError:
        return ConfigError(f"{label}: {what}; not a checkpoint march wrote (retrain or restore it)")

    it = payload.get("iteration")
    if type(it) is not int or not 0 <= it <= ITERATION_MAX:
        raise refuse(f"its iteration {it!r} is not a whole number in [0, {ITERATION_MAX}]")
    steps = payload.get("env_steps")
    if type(steps) is not int or steps < 0:
        raise refuse(f"its env_steps {steps!r} is not a whole number >= 0")
    wall = payload.get("wall_s", 0.0)
    if type(wall) not in (int, float) or not 0 <= wall < float("inf"):
        raise refuse(f"its wall_s {wall!r} is not a finite number >= 0")
    raw = payload.get("config")
    if raw is None:
        return None
    if not isinstance(raw, dict):
        raise refuse(f"its config is a {type(raw).__name__}, not a mapping")
    bad = interpolations(raw)
    if bad:
        raise refuse(f"its config key {bad[0]} holds a '${{...}}' interpolation or resolver")
    if named is not None:
        check_named_modules(raw.get("extra_modules"), named, label)
    try:
        cfg = to_march_config(OmegaConf.merge(OmegaConf.structured(MarchConfig), raw))
    except ConfigError as err:
        raise refuse(f"its config is not valid: {err}") from None
    except Exception as err:  # noqa: BLE001 - any malformed config is the same error
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise refuse(f"its config is not valid ({first})") from None
    check_memory(cfg, f"{label}: its config: ")
    section = cfg.teacher if kind == "teacher" else cfg.distill
    per_it = section.num_steps_per_env * cfg.compute.num_envs
    limit = cfg.teacher.iterations if kind == "teacher" else cfg.distill.max_iterations
    if it > limit:
        raise refuse(f"its iteration {it} is past its config's {limit} iterations")
    if steps < it * per_it or steps % per_it:
        raise refuse(
            f"its env_steps {steps} is not a multiple of {per_it} (steps x envs of an "
            f"iteration) of at least iteration x {per_it}"
        )
    return cfg


LAYOUT_KEYS = {
    "teacher": ("actor_obs_dim", "num_actions"),
    "student": ("proprio_dim", "history_len", "num_actions"),
}
"""Whole-number entries of a checkpoint's ``layout`` (sizes of its network's inputs/outputs)."""
LAYOUT_MAX = 1 << 20
"""No observation or action of a G1 policy is anywhere near this long."""


def _expected_network(payload: dict[str, Any], kind: str, cfg: MarchConfig) -> torch.nn.Module:
    """The network a checkpoint's config and layout describe, on the ``meta`` device."""
    # Imported before the meta context: their modules build tensors (and read them) at import.
    from rsl_rl.models import MLPModel
    from tensordict import TensorDict

    from march.policies.student import StudentPolicy

    lay = payload["layout"]
    with torch.device("meta"):
        if kind == "student":
            return StudentPolicy.from_layout(cfg.student, lay)
        actor_cfg = copy.deepcopy(payload["ppo"]["actor"])  # rsl-rl pops from nested dicts
        actor_cfg.pop("class_name", None)
        obs = TensorDict({"actor": torch.zeros(1, lay["actor_obs_dim"])}, batch_size=[1])
        return MLPModel(obs, {"actor": ["actor"]}, "actor", lay["num_actions"], **actor_cfg)


def network_weights(payload: dict[str, Any], kind: str, cfg: MarchConfig) -> dict[str, Any]:
    """Zero weights of the network ``payload``'s layout (and ``ppo``) and ``cfg`` describe, on
    the CPU: what :func:`check_weights` compares a checkpoint with (tests build payloads)."""
    net = _expected_network(payload, kind, cfg).to_empty(device="cpu")
    return {k: torch.zeros_like(v) for k, v in net.state_dict().items()}


def check_weights(payload: dict[str, Any], kind: str, label: str, cfg: MarchConfig | None) -> None:
    """The checkpoint's weights are the network its config and layout describe: layout entries
    whole numbers that agree with the config, every tensor present with its shape, none extra.
    ``cfg``: the checkpoint's config (None: an older checkpoint; only the layout is checked)."""

    def refuse(what: str) -> ConfigError:
        return ConfigError(f"{label}: {what}; its weights do not fit its config (retrain it)")

    lay = payload.get("layout")
    if not isinstance(lay, dict):
        raise refuse("it has no 'layout' (observation and action sizes)")
    for key in LAYOUT_KEYS[kind]:
        v = lay.get(key)
        if type(v) is not int or not 0 < v <= LAYOUT_MAX:
            raise refuse(f"its layout.{key} {v!r} is not a whole number in [1, {LAYOUT_MAX}]")
    states = {"teacher": "actor_state_dict", "student": "student_state_dict"}
    weights = payload.get(states[kind])
    if not isinstance(weights, dict) or not all(
        isinstance(v, torch.Tensor) for v in weights.values()
    ):
        raise refuse(f"its '{states[kind]}' is not a mapping of tensors")
    if cfg is None:
        return
    if kind == "student":
        hw = lay.get("image_hw")
        if not (isinstance(hw, list) and len(hw) == 2 and all(type(x) is int for x in hw)):
            raise refuse(f"its layout.image_hw {hw!r} is not [height, width]")
        agree = {
            "variant": (lay.get("variant"), cfg.student.variant, "student.variant"),
            "history_len": (lay["history_len"], cfg.env.history_length, "env.history_length"),
            "image_hw": (hw, [cfg.depth.height, cfg.depth.width], "[depth.height, depth.width]"),
        }
    else:
        ppo = payload.get("ppo")
        actor = ppo.get("actor") if isinstance(ppo, dict) else None
        if not isinstance(actor, dict) or not isinstance(actor.get("hidden_dims"), list):
            raise refuse("its 'ppo' entry does not describe the actor network")
        agree = {
            "ppo.actor.hidden_dims": (
                list(actor["hidden_dims"]),
                list(cfg.teacher.hidden_dims),
                "teacher.hidden_dims",
            )
        }
    for key, (theirs, mine, where) in agree.items():
        if theirs != mine:
            raise refuse(f"its layout {key} {theirs!r} is not its config's {where} {mine!r}")
    try:
        expected = {
            k: tuple(v.shape) for k, v in _expected_network(payload, kind, cfg).state_dict().items()
        }
    except Exception as err:  # noqa: BLE001 - a network its config cannot describe
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise refuse(f"its config and layout describe no network ({first})") from None
    got = {k: tuple(v.shape) for k, v in weights.items()}
    missing = sorted(set(expected) - set(got))
    extra = sorted(set(got) - set(expected))
    if missing or extra:
        which = f"lacks {missing[0]}" if missing else f"holds {extra[0]}, which its network has not"
        raise refuse(f"its {states[kind]} {which}")
    for k in expected:
        if expected[k] != got[k]:
            raise refuse(
                f"{states[kind]}[{k!r}] has shape {list(got[k])}, its config's network {list(expected[k])}"
            )


def read_checkpoint(
    path: str,
    kind: str,
    named: Sequence[str],
    device: str = "cpu",
    source: str | None = None,
    world_mismatch: Callable[[dict], str | None] | None = None,
) -> tuple[dict[str, Any], MarchConfig | None]:
    """A checkpoint through every check of this module: (payload on ``device``, its config).

    ``named``: the modules the user named (their config's ``extra_modules``); ``source``: how
    messages name the file (default ``<kind>_ckpt=<path>``); ``world_mismatch``: why this
    process group cannot resume the payload (a resume; checked first). Raises
    :class:`CheckpointError` (the file) or :class:`ConfigError` (its contents), one line each.
    """
    label = source or f"{kind}_ckpt={path}"
    payload = load_checkpoint(path, kind, device, source=label)
    if world_mismatch is not None and (why := world_mismatch(payload)):  # issue 37
        raise CheckpointError(f"{label}: {why}")
    saved = check_checkpoint(payload, kind, label, named)
    check_weights(payload, kind, label, saved)
    return payload, saved


def policy_from_checkpoint(
    cfg: MarchConfig,
    kind: str,
    path: str,
    explicit_overrides: Sequence[str],
    *,
    distill: bool = False,
    device: str = "cpu",
    payload: dict[str, Any] | None = None,
) -> tuple[dict[str, Any], MarchConfig, list[str]]:
    """(payload, config to run with, one line per policy field the checkpoint changed): the
    checkpoint through the checks of :func:`read_checkpoint` (``payload``: already read, checked
    again), its policy applied (:func:`march.store.provenance.apply_checkpoint_config`; an
    explicit command-line choice that contradicts it is one line, said before the weights)."""
    label = f"{kind}_ckpt={path}"
    if payload is None:
        payload = load_checkpoint(path, kind, device, source=label)
    saved = check_checkpoint(payload, kind, label, cfg.extra_modules)
    # A command-line choice that contradicts the checkpoint is said first (the user's fix is on
    # the command line); then its weights against its config, still before any env.
    new = apply_checkpoint_config(cfg, payload, explicit_overrides, path, kind, distill=distill)
    check_weights(payload, kind, label, saved)
    notes = [
        f"[checkpoint] {label} defines the policy: {c}" for c in policy_changes(cfg, new, kind)
    ]
    return payload, new, notes


def policy_checkpoint(cfg: MarchConfig) -> tuple[str, str, bool] | None:
    """(kind, path, distill) of the checkpoint that defines a ``march.train`` run's policy.

    stage=eval: the evaluated checkpoint. stage=student: the teacher, whose reward set and
    observation layout the distillation env must have (the "teacher reward on student rollouts"
    is that reward); the run's own student and curriculum stay the command line's.
    """
    if cfg.stage == "eval":
        kind = cfg.eval.policy
        path = cfg.student_ckpt if kind == "student" else cfg.teacher_ckpt
        return (kind, path, False) if path else None
    if cfg.stage == "student" and cfg.teacher_ckpt:
        return "teacher", cfg.teacher_ckpt, True
    return None


def apply_policy_checkpoint(
    cfg: MarchConfig, explicit_overrides: Sequence[str], payload: dict[str, Any] | None = None
) -> tuple[MarchConfig, list[str]]:
    """``cfg`` with its policy taken from the checkpoint its ``march.train`` stage runs
    (:func:`policy_checkpoint`), and one line per value the checkpoint changed."""
    which = policy_checkpoint(cfg)
    if which is None:
        return cfg, []
    kind, path, distill = which
    _, new, notes = policy_from_checkpoint(
        cfg, kind, path, explicit_overrides, distill=distill, payload=payload
    )
    return new, notes


__all__ = [
    "CheckpointError",
    "apply_policy_checkpoint",
    "check_checkpoint_files",
    "check_checkpoint",
    "check_named_modules",
    "check_weights",
    "policy_checkpoint",
    "policy_from_checkpoint",
    "read_checkpoint",
]
