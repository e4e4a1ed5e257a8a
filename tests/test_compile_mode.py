"""compute.compile_mode (march.compiled_math.set_compile_mode): ``reduce-overhead`` compiles with
CUDA-graph capture, and no output a caller holds is overwritten by the next replay.

A CUDA graph replays into the memory of its first capture. That cannot happen on CPU (torch skips
the capture there), so the replay is imitated: a stand-in for ``torch.compile`` whose compiled
function writes every result into one buffer it owns, as a graph replay does."""

from __future__ import annotations

import pytest
import torch

from march import compiled_math
from march.compiled_math import COMPILE_MODES, compile_mode, fused, set_compile_mode


def _affine(x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    return x * 2.0 + y, (x - y).abs()


@pytest.fixture
def replaying_compile(monkeypatch):
    """torch.compile replaced by a 'compiler' whose outputs live in one buffer per output,
    rewritten on every call (a CUDA graph replay), recording the mode it was asked for."""
    asked: list[dict] = []

    def fake_compile(fn, **kwargs):
        asked.append(kwargs)
        buffers: list[torch.Tensor] = []

        def replay(*args, **kw):
            outs = fn(*args, **kw)
            if not buffers:
                buffers.extend(torch.empty_like(o) for o in outs)
            for buf, o in zip(buffers, outs, strict=True):
                buf.copy_(o)
            return tuple(buffers)

        return replay

    monkeypatch.setattr(torch, "compile", fake_compile)
    monkeypatch.setattr(compiled_math, "_COMPILED", {})
    before = compile_mode()
    yield asked
    set_compile_mode(before)


@pytest.mark.parametrize("inference", [True, False])
def test_reduce_overhead_outputs_survive_the_next_replay(replaying_compile, inference):
    """Over many generated calls every output a caller kept still holds its own call's result,
    inside inference mode (the teacher's rollouts) and outside it (evaluation, distillation)."""
    set_compile_mode("reduce-overhead")
    fn = fused(_affine)
    assert replaying_compile == [{"dynamic": True, "mode": "reduce-overhead"}]
    gen = torch.Generator().manual_seed(7)
    kept, want = [], []
    for _ in range(25):
        x, y = torch.randn(5, 3, generator=gen), torch.randn(5, 3, generator=gen)
        if inference:
            with torch.inference_mode():
                out = fn(x, y)
        else:
            out = fn(x, y)
        kept.append(out)
        want.append(_affine(x, y))
    for got, exp in zip(kept, want, strict=True):
        torch.testing.assert_close(got, exp, rtol=0, atol=0)


def test_the_default_mode_keeps_its_compile_options(replaying_compile):
    set_compile_mode("default")
    fused(_affine)
    assert replaying_compile == [
        {"dynamic": True, "options": compiled_math.INDUCTOR_OPTIONS},
    ]


def test_each_mode_compiles_its_own_function_once(replaying_compile):
    set_compile_mode("default")
    a = fused(_affine)
    set_compile_mode("reduce-overhead")
    b = fused(_affine)
    assert fused(_affine) is b and a is not b
    set_compile_mode("default")
    assert fused(_affine) is a
    assert [k.get("mode") for k in replaying_compile] == [None, "reduce-overhead"]


def test_an_unknown_mode_is_refused_and_the_config_knows_the_same_modes():
    with pytest.raises(ValueError, match="max-autotune"):
        set_compile_mode("max-autotune")
    from march.config.cli import load
    from march.errors import ConfigError

    for mode in COMPILE_MODES:
        assert load(["compute=smoke", f"compute.compile_mode={mode}"]).compute.compile_mode == mode
    with pytest.raises(ConfigError, match="compile_mode"):
        load(["compute=smoke", "compute.compile_mode=max-autotune"])


@pytest.mark.slow
def test_reduce_overhead_on_cpu_computes_the_eager_numbers():
    """Real inductor, mode reduce-overhead, on CPU (no capture applies): the eager numbers."""
    before = compile_mode()
    try:
        set_compile_mode("reduce-overhead")
        fn = fused(_affine)
        gen = torch.Generator().manual_seed(1)
        for n in (4, 9, 4):
            x, y = torch.randn(n, 3, generator=gen), torch.randn(n, 3, generator=gen)
            for got, want in zip(fn(x, y), _affine(x, y), strict=True):
                torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-6)
    finally:
        set_compile_mode(before)
