"""Export a student's ``act_inference`` to ONNX, check it against torch, time it on one CPU thread.

The exported graph takes ``proprio_hist`` (B, history_len, proprio_dim), ``command``
(B, command_dim) and ``depth`` (B, 1, H, W) (float32, batch axis dynamic) and returns ``actions``
(B, A). The observation normalisers are part of the graph (their running statistics are baked in as
constants), so deployment feeds raw observations. ``metadata_props`` carry the caller's metadata
(observation and action layout) plus the input shapes and the student variant.

Exporter: torch 2.13 defaults to the dynamo exporter; we use the TorchScript-based exporter
(``dynamo=False``), which handles ``nn.TransformerEncoder`` and writes one self-contained file.

Two graphs of the same maths (``graph=``): ``deploy`` (default), :class:`DeployGraph`, the fast
batch-1 CPU graph (the last encoder layer computes only the CLS row the policy reads; attention
without shape arithmetic), and ``trace``, the traced ``act_inference`` as training runs it. Parity
is always measured against the policy's own ``act_inference``; :func:`compare_graphs` times both
(README, "Deploy: sim-to-sim").
"""

from __future__ import annotations

import copy
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import onnxruntime as ort
import torch
from torch import nn

from march.policies.student import StudentPolicy

INPUT_NAMES = ("proprio_hist", "command", "depth")
OUTPUT_NAME = "actions"
DEFAULT_OPSET = 17
GRAPHS = ("deploy", "trace")
"""``deploy``: :class:`DeployGraph` (fast batch-1 CPU graph, same maths); ``trace``: the traced
``act_inference`` as it runs in training (the pre-optimisation export, kept for comparison)."""


class ActInferenceWrapper(nn.Module):
    """Module whose forward is the policy's deterministic ``act_inference``."""

    def __init__(self, policy: StudentPolicy) -> None:
        super().__init__()
        self.policy = policy

    def forward(
        self, proprio_hist: torch.Tensor, command: torch.Tensor, depth: torch.Tensor
    ) -> torch.Tensor:
        return self.policy.act_inference(proprio_hist, command, depth)


class DeployGraph(nn.Module):
    """``act_inference`` of a student, written for a fast batch-1 CPU graph (same maths).

    What it changes against tracing ``policy.act_inference`` (measured in the README's
    "Deploy: sim-to-sim" section):

    - the **last transformer layer computes only the CLS row**: the policy reads nothing but
      the CLS output, so the last layer's queries, attention output, feed-forward and norms of
      the other tokens (55 tokens for the G1 student, 54 of them unused) are dead work; its keys
      and values still come from every token. This drops ~40% of the matrix products;
    - **attention written out** with constant head reshapes (``reshape(-1, n, heads, d_head)``)
      instead of ``nn.MultiheadAttention``'s traced graph, whose shape arithmetic
      (Shape/Gather/Unsqueeze/Concat per layer) was ~15% of a call; tokens travel as 2-D rows
      (B * N, d), so every projection is one Gemm with its bias fused;
    - the MDN's log-std head (unused by the top-mode mean) is left out.

    Variants without a transformer (``no_transformer``) keep the policy's own path.
    """

    def __init__(self, policy: StudentPolicy) -> None:
        super().__init__()
        self.policy = policy
        self.has_transformer = hasattr(policy, "transformer")
        if self.has_transformer:
            for layer in policy.transformer.layers:
                if not layer.norm_first or layer.self_attn.batch_first is not True:
                    raise ValueError("DeployGraph expects pre-LN, batch-first encoder layers")

    def _heads(self, t: torch.Tensor, rows: int) -> torch.Tensor:
        """(B * rows, d) -> (B, heads, rows, d_head)."""
        h = self.policy.cfg.n_heads
        return t.reshape(-1, rows, h, self.policy.cfg.d_model // h).transpose(1, 2)

    def _layer(self, layer: nn.Module, x: torch.Tensor, cls_only: bool) -> torch.Tensor:
        """One pre-LN encoder layer on token rows ``x`` (B * N, d): 2-D products, so that
        onnxruntime runs each projection as one Gemm with its bias fused. ``cls_only``: queries,
        attention output and feed-forward for the CLS row alone; returns (B, d) then."""
        att = layer.self_attn
        d, n = att.embed_dim, self.policy.num_tokens
        w, b = att.in_proj_weight, att.in_proj_bias
        lin = torch.nn.functional.linear
        y = layer.norm1(x)
        k = self._heads(lin(y, w[d : 2 * d], b[d : 2 * d]), n)
        v = self._heads(lin(y, w[2 * d :], b[2 * d :]), n)
        if cls_only:
            x = x.reshape(-1, n, d)[:, 0]  # (B, d): the CLS row of every batch element
            y = y.reshape(-1, n, d)[:, 0]
        rows = 1 if cls_only else n
        q = self._heads(lin(y, w[:d], b[:d]), rows) * (d // att.num_heads) ** -0.5
        a = torch.softmax(q @ k.transpose(2, 3), dim=-1) @ v  # (B, heads, rows, d_head)
        x = x + att.out_proj(a.transpose(1, 2).reshape(-1, d))
        return x + layer.linear2(layer.activation(layer.linear1(layer.norm2(x))))

    def forward(
        self, proprio_hist: torch.Tensor, command: torch.Tensor, depth: torch.Tensor
    ) -> torch.Tensor:
        p = self.policy
        if not self.has_transformer:
            return p.act_inference(proprio_hist, command, depth)
        d = p.cfg.d_model
        pn = p.proprio_normalizer(proprio_hist)
        c = p.command_normalizer(command)
        hist = p.proprio_proj(pn.reshape(-1, p.proprio_dim))
        cmd = p.command_proj(c)
        cls = cmd * 0.0 + p.cls_token[0]  # (B, d) by broadcasting, no Shape/Expand
        seq = [cls.unsqueeze(1), cmd.unsqueeze(1), hist.reshape(-1, p.history_len, d)]
        if p.cnn is not None:  # image: none reads no image (the input stays, see _keep_inputs)
            fmap = p.cnn(depth).reshape(-1, p.cnn_out_channels, p.num_image_tokens)
            img = p.image_proj(fmap.transpose(1, 2).reshape(-1, p.cnn_out_channels))
            seq.append(img.reshape(-1, p.num_image_tokens, d))
        x = torch.cat(seq, dim=1)
        x = (x + p.pos_embed).reshape(-1, d)  # token rows (B * N, d)
        layers = list(p.transformer.layers)
        for i, layer in enumerate(layers):
            x = self._layer(layer, x, cls_only=i == len(layers) - 1)
        z = p.head_mlp(p.out_norm(x))  # the CLS rows (B, d)
        if not p.is_mdn:
            return p.action_out(z)
        # top_mode_mean: the argmax mode's block of the flat (B, K * A) means
        a = p.num_actions
        idx = torch.argmax(p.mdn.logits(z), dim=-1, keepdim=True)  # (B, 1)
        cols = idx * a + torch.arange(a, device=z.device)  # (B, A)
        return torch.gather(p.mdn.means(z), 1, cols)


def example_inputs(
    policy: StudentPolicy, batch_size: int = 1, generator: torch.Generator | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Random float32 CPU inputs of the policy's shapes (depth uniform in [0, 1], as the env feeds it)."""
    h, w = policy.image_hw
    proprio = torch.randn(batch_size, policy.history_len, policy.proprio_dim, generator=generator)
    command = torch.randn(batch_size, policy.command_dim, generator=generator)
    depth = torch.rand(batch_size, 1, h, w, generator=generator)
    return proprio, command, depth


def _session(path: Path, threads: int = 1) -> ort.InferenceSession:
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = threads
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])


def _feeds(inputs: tuple[torch.Tensor, ...]) -> dict[str, np.ndarray]:
    return {n: t.numpy().astype(np.float32) for n, t in zip(INPUT_NAMES, inputs, strict=True)}


def _export(model: nn.Module, dummy: tuple[torch.Tensor, ...], path: Path, opset: int) -> None:
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # TorchScript-exporter deprecation / tracer warnings
        torch.onnx.export(
            model,
            dummy,
            str(path),
            dynamo=False,
            input_names=list(INPUT_NAMES),
            output_names=[OUTPUT_NAME],
            dynamic_axes={n: {0: "batch"} for n in (*INPUT_NAMES, OUTPUT_NAME)},
            opset_version=opset,
            do_constant_folding=True,
        )
    _keep_inputs(path, dummy)


def _keep_inputs(path: Path, dummy: tuple[torch.Tensor, ...]) -> None:
    """Every variant's graph takes the same named inputs: the exporter drops an input the
    network does not read (a student with ``image: none`` ignores ``depth``), so add it back
    as an unused graph input of the same shape (valid ONNX; onnxruntime accepts the feed)."""
    model = onnx.load(str(path))
    have = {i.name for i in model.graph.input}
    missing = [(n, t) for n, t in zip(INPUT_NAMES, dummy, strict=True) if n not in have]
    if not missing:
        return
    for name, tensor in missing:
        shape = ["batch", *tensor.shape[1:]]
        info = onnx.helper.make_tensor_value_info(name, onnx.TensorProto.FLOAT, shape)
        model.graph.input.append(info)
    order = {n: i for i, n in enumerate(INPUT_NAMES)}
    inputs = sorted(model.graph.input, key=lambda i: order.get(i.name, len(order)))
    del model.graph.input[:]
    model.graph.input.extend(inputs)
    onnx.save(model, str(path))


def export_student_onnx(
    policy: StudentPolicy,
    path: str | Path,
    metadata: dict[str, str],
    *,
    opset: int = DEFAULT_OPSET,
    check_batch_sizes: tuple[int, ...] = (1, 16),
    latency_calls: int = 200,
    warmup_calls: int = 20,
    seed: int = 0,
    graph: str = "deploy",
) -> dict[str, Any]:
    """Export ``policy.act_inference`` to ``path`` and verify it with onnxruntime.

    The policy is deep-copied to CPU in eval mode, so the caller's module (device, train mode)
    is untouched. Returns ``{"max_abs_diff", "latency_ms_median", "latency_ms_p95", "path", ...}``:
    the max |onnxruntime - torch| over random inputs at ``check_batch_sizes`` and the per-call
    latency (batch 1, one intra-op thread) over ``latency_calls`` calls after ``warmup_calls``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    bad = {k: v for k, v in metadata.items() if not isinstance(k, str) or not isinstance(v, str)}
    if bad:
        raise TypeError(f"metadata must map str -> str; offending entries: {bad}")

    if graph not in GRAPHS:
        raise ValueError(f"graph={graph!r}; choose one of {GRAPHS}")
    reference = ActInferenceWrapper(copy.deepcopy(policy).to("cpu").float()).eval()
    # parity is always against the policy's own act_inference, whichever graph is written
    model = DeployGraph(reference.policy).eval() if graph == "deploy" else reference
    gen = torch.Generator().manual_seed(seed)
    dummy = example_inputs(model.policy, 1, gen)
    fastpath = torch.backends.mha.get_fastpath_enabled()
    # the fused encoder kernel (aten::_transformer_encoder_layer_fwd) has no ONNX symbolic:
    # trace the composite path instead (same maths), then restore the global flag
    torch.backends.mha.set_fastpath_enabled(False)
    try:
        _export(model, dummy, path, opset)
    finally:
        torch.backends.mha.set_fastpath_enabled(fastpath)

    p = model.policy
    props = {
        "student_variant": p.variant,
        "input_proprio_hist": f"float32[batch,{p.history_len},{p.proprio_dim}]",
        "input_command": f"float32[batch,{p.command_dim}]",
        "input_depth": f"float32[batch,1,{p.image_hw[0]},{p.image_hw[1]}] normalised to [0, 1] over the camera range",
        "output_actions": f"float32[batch,{p.num_actions}]",
        "inference_mode": "top_mode_mean" if p.is_mdn else "deterministic",
        "observation_normalization": "embedded",
        "export_graph": graph,
        **metadata,
    }
    proto = onnx.load(str(path))
    existing = {e.key: e.value for e in proto.metadata_props}
    onnx.helper.set_model_props(proto, {**existing, **props})
    onnx.checker.check_model(proto)
    onnx.save(proto, str(path))

    sess = _session(path, threads=1)
    max_diff = 0.0
    with torch.no_grad():
        for bs in check_batch_sizes:
            inputs = example_inputs(p, bs, gen)
            ref = reference(*inputs).numpy()
            got = sess.run([OUTPUT_NAME], _feeds(inputs))[0]
            if got.shape != ref.shape:
                raise RuntimeError(f"ONNX output shape {got.shape} != torch {ref.shape}")
            max_diff = max(max_diff, float(np.max(np.abs(got - ref))))

    feeds = _feeds(example_inputs(p, 1, gen))
    for _ in range(warmup_calls):
        sess.run([OUTPUT_NAME], feeds)
    times = np.empty(latency_calls)
    for i in range(latency_calls):
        t0 = time.perf_counter()
        sess.run([OUTPUT_NAME], feeds)
        times[i] = (time.perf_counter() - t0) * 1e3

    return {
        "max_abs_diff": max_diff,
        "latency_ms_median": float(np.median(times)),
        "latency_ms_p95": float(np.percentile(times, 95)),
        "path": str(path),
        "opset": opset,
        "graph": graph,
        "num_params": p.num_params(),
        "metadata_keys": sorted(props),
    }


def read_onnx_metadata(path: str | Path) -> dict[str, str]:
    """The ``metadata_props`` of an ONNX file as a dict."""
    return {e.key: e.value for e in onnx.load(str(path)).metadata_props}


def compare_graphs(
    policy: StudentPolicy, directory: str | Path, calls: int = 2000, seed: int = 0
) -> dict[str, dict[str, float]]:
    """Export ``policy`` as both graphs into ``directory`` and time them on one CPU thread.

    The two sessions run interleaved (call by call, same inputs, after 50 warm-up calls each),
    so load from other processes falls on both alike. Per graph: ``median_ms``, ``p10_ms``,
    ``p95_ms``, ``min_ms`` (batch 1) and ``max_abs_diff`` against the policy.
    """
    directory = Path(directory)
    out: dict[str, dict[str, float]] = {}
    sessions = {}
    for graph in GRAPHS:
        res = export_student_onnx(policy, directory / f"{graph}.onnx", {}, graph=graph, seed=seed)
        out[graph] = {"max_abs_diff": res["max_abs_diff"]}
        sessions[graph] = _session(Path(res["path"]), threads=1)
    gen = torch.Generator().manual_seed(seed + 1)
    feeds = _feeds(example_inputs(copy.deepcopy(policy).cpu().float(), 1, gen))
    for sess in sessions.values():
        for _ in range(50):
            sess.run([OUTPUT_NAME], feeds)
    times = {g: np.empty(calls) for g in sessions}
    for i in range(calls):
        for graph, sess in sessions.items():
            t0 = time.perf_counter()
            sess.run([OUTPUT_NAME], feeds)
            times[graph][i] = (time.perf_counter() - t0) * 1e3
    for graph, t in times.items():
        out[graph].update(
            median_ms=float(np.median(t)),
            p10_ms=float(np.percentile(t, 10)),
            p95_ms=float(np.percentile(t, 95)),
            min_ms=float(np.min(t)),
        )
    return out
