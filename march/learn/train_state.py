"""A run's whole training state beyond the networks: collected into a checkpoint, given back on
resume, on the same device or another one.

:func:`collect_state` returns the checkpoint entries ``curriculum`` and ``episode`` (from
:mod:`march.env.env_state`) and ``streams``: every random stream the run draws from

- ``torch``: torch's CPU generator (also the payload's ``rng``, kept for older readers);
- ``cuda``: the run device's default CUDA generator (CUDA runs only);
- ``numpy`` and ``python``: the global numpy and ``random`` states;
- ``planner``: the reference command's planner generator (on the env device);
- any generator the runner names (the distillation's ``distill`` generator);
- ``device``: the device the states were taken on.

:func:`restore_state` puts them back. A CPU generator's state (5056 bytes) and a CUDA one's
(16 bytes: seed and offset) are different formats, and neither can continue the other's stream:
a stream that cannot be carried to the new device is reseeded from the run's seed, the
iteration and the stream's name (:func:`stream_seed`), and the resume says so in one line.
"""

from __future__ import annotations

import random
import zlib
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from march.env.env_state import (
    EnvStateError,
    env_state,
    levels_digest,
    mean_terrain_level,
    planner_generator,
    restore_env_state,
)
from march.learn import distributed
from march.store.checkpoint import CheckpointError

if TYPE_CHECKING:
    from mjlab.envs import ManagerBasedRlEnv

STATE_KEYS = ("curriculum", "episode", "streams")
CUDA_STATE_BYTES = 16
"""A CUDA (Philox) generator's state: seed and offset, 8 bytes each."""
__all__ = [
    "STATE_KEYS",
    "collect_state",
    "collect_streams",
    "mean_terrain_level",
    "rank_payload",
    "restore_state",
    "restore_streams",
    "stream_seed",
]


def stream_seed(seed: int, iteration: int, name: str) -> int:
    """The deterministic seed of stream ``name`` reseeded at ``iteration`` of a run of ``seed``."""
    return (int(seed) * 1_000_003 + int(iteration) * 7919 + zlib.crc32(name.encode())) % 2**62


def _numpy_state() -> dict[str, Any]:
    kind, keys, pos, has_gauss, cached = np.random.get_state()
    return {
        "kind": str(kind),
        "keys": torch.from_numpy(np.asarray(keys, dtype=np.int64)),
        "pos": int(pos),
        "has_gauss": int(has_gauss),
        "cached_gaussian": float(cached),
    }


def _python_state() -> dict[str, Any]:
    version, internal, gauss = random.getstate()
    return {
        "version": int(version),
        "internal": torch.tensor(internal, dtype=torch.int64),
        "gauss_next": gauss,
    }


def collect_streams(device: str, generators: dict[str, torch.Generator]) -> dict[str, Any]:
    """The ``streams`` entry: the process's generators plus ``generators`` (by name)."""
    streams: dict[str, Any] = {
        "device": str(device),
        "torch": torch.get_rng_state(),
        "numpy": _numpy_state(),
        "python": _python_state(),
    }
    if str(device).startswith("cuda"):
        streams["cuda"] = torch.cuda.get_rng_state(device)
    for name, gen in generators.items():
        streams[name] = gen.get_state()
    return streams


def _generators(
    env: ManagerBasedRlEnv, extra: dict[str, torch.Generator] | None
) -> dict[str, torch.Generator]:
    planner = planner_generator(env)
    return {**({"planner": planner} if planner is not None else {}), **(extra or {})}


def collect_state(
    env: ManagerBasedRlEnv, device: str, generators: dict[str, torch.Generator] | None = None
) -> dict[str, Any]:
    """The ``curriculum``, ``episode`` and ``streams`` entries of a checkpoint (plain data)."""
    return {**env_state(env), "streams": collect_streams(device, _generators(env, generators))}


def _rng_tensor(value: Any, name: str, where: str) -> torch.Tensor:
    if not (isinstance(value, torch.Tensor) and value.dtype == torch.uint8 and value.dim() == 1):
        raise CheckpointError(f"{where}: 'streams.{name}' is not a torch RNG state (1-D uint8)")
    return value.to("cpu").contiguous()


def _set_generator(
    gen: torch.Generator, state: Any, name: str, reseed: int, where: str, moved: list[str]
) -> None:
    """``gen`` continues the saved stream when the state is in its format, else is reseeded."""
    state = _rng_tensor(state, name, where)
    if state.numel() == gen.get_state().numel():
        gen.set_state(state)
    else:
        gen.manual_seed(reseed)
        moved.append(name)


def _restore_numpy(state: Any, where: str) -> None:
    try:
        keys = state["keys"].to(torch.int64).numpy().astype(np.uint32)
        np.random.set_state(
            (
                str(state["kind"]),
                keys,
                int(state["pos"]),
                int(state["has_gauss"]),
                float(state["cached_gaussian"]),
            )
        )
    except (KeyError, TypeError, ValueError, AttributeError) as err:
        raise CheckpointError(
            f"{where}: 'streams.numpy' is not a numpy RNG state ({err})"
        ) from None


def _restore_python(state: Any, where: str) -> None:
    try:
        internal = tuple(int(x) for x in state["internal"].tolist())
        gauss = state["gauss_next"]
        random.setstate((int(state["version"]), internal, None if gauss is None else float(gauss)))
    except (KeyError, TypeError, ValueError, AttributeError) as err:
        raise CheckpointError(f"{where}: 'streams.python' is not a random state ({err})") from None


def restore_streams(
    streams: dict[str, Any],
    device: str,
    seed: int,
    iteration: int,
    where: str,
    generators: dict[str, torch.Generator],
) -> str | None:
    """Put the saved streams back; a stream that cannot be carried to ``device`` is reseeded
    with :func:`stream_seed`. Returns the one line that says so (None: every stream continued).
    A generator whose state is missing is left as it is (an older checkpoint)."""
    moved: list[str] = []
    dropped = ""
    saved_dev = str(streams.get("device", device))
    if streams.get("torch") is not None:
        torch.set_rng_state(_rng_tensor(streams["torch"], "torch", where))
    if "numpy" in streams:
        _restore_numpy(streams["numpy"], where)
    if "python" in streams:
        _restore_python(streams["python"], where)
    if str(device).startswith("cuda"):
        cuda = streams.get("cuda")
        if cuda is not None and _rng_tensor(cuda, "cuda", where).numel() == CUDA_STATE_BYTES:
            torch.cuda.set_rng_state(_rng_tensor(cuda, "cuda", where), device)
        else:
            with torch.cuda.device(device):
                torch.cuda.manual_seed(stream_seed(seed, iteration, "cuda"))
            moved.append("cuda")
    elif "cuda" in streams:
        dropped = "; the CUDA generator's stream has no place on the CPU (its draws now come "
        dropped += "from the restored CPU generator)"
    for name, gen in generators.items():
        if name in streams:
            reseed = stream_seed(seed, iteration, name)
            _set_generator(gen, streams[name], name, reseed, where, moved)
    if not (moved or dropped):
        return None
    said = (
        f"the stream(s) {', '.join(moved)} cannot continue across devices: reseeded from seed "
        f"{seed} and iteration {iteration}"
        if moved
        else "every stream continues"
    )
    return f"saved on {saved_dev}, resumed on {device}: {said}{dropped}"


def restore_state(
    env: ManagerBasedRlEnv,
    payload: dict[str, Any],
    device: str,
    seed: int,
    where: str,
    generators: dict[str, torch.Generator] | None = None,
) -> list[str]:
    """Give a freshly built env and the process back a checkpoint's state; returns the lines to
    print (levels restored, streams reseeded). ``where`` names the checkpoint in errors."""
    try:
        notes = restore_env_state(env, payload)
    except EnvStateError as err:
        raise CheckpointError(f"{where}: {err}; it does not fit this run's env") from None
    if isinstance(payload.get("curriculum"), dict):
        lv = env.scene.terrain.terrain_levels
        notes.append(
            f"curriculum: {env.num_envs} envs start from their saved terrain levels (mean "
            f"{float(lv.float().mean()):.3g}, digest {levels_digest(lv)})"
        )
    streams = payload.get("streams")
    if not isinstance(streams, dict):
        # An older checkpoint: only the CPU generator (and the distillation's) were saved.
        streams = {"device": str(device), "torch": payload.get("rng")}
        streams.update(
            {k: payload["generator"] for k in generators or {} if "generator" in payload}
        )
        notes.append("the checkpoint holds no numpy, python or planner streams (an older run)")
    iteration = int(payload.get("iteration", 0))
    line = restore_streams(streams, device, seed, iteration, where, _generators(env, generators))
    return notes + ([line] if line else [])


def rank_payload(payload: dict[str, Any], where: str) -> dict[str, Any]:
    """The checkpoint as this rank resumes it: its own ``rank_states`` entry (levels, clocks,
    commands, streams) in place of rank 0's. A checkpoint written by another number of ranks is
    refused in one line (:func:`march.learn.distributed.world_mismatch`)."""
    if why := distributed.world_mismatch(payload):
        raise CheckpointError(f"{where}: {why}")
    return distributed.own_rank_state(payload)
