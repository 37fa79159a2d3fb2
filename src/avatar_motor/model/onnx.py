"""The denoiser as an ONNX graph, run by ONNX Runtime on the CPU (RuntimeConfig.backend
"onnxruntime"), and the file an engine loads (Unity Sentis, Unreal NNE; docs/onnx.md).

Graph: inputs `t` (B,) int64 diffusion step, `x_t` (B, frames, 267) float32 noisy normalised
segment, `x0` (B, 267) float32 normalised initial state, and for an EMDM generator `z` (B, latent)
float32 its latent, drawn from N(0, I) at every step; output `x0_hat` (B, frames, 267) float32,
the network's estimate of the clean normalised segment. B is dynamic.

`quantize_int8` makes the graph with int8 weights that `RuntimeConfig.int8_weights` runs (an
option: docs/onnx.md), with the same inputs and output.
"""
from __future__ import annotations

import io
import logging
import warnings
import weakref
from pathlib import Path

import numpy as np
import torch

from ..io.atomic import write_file
from .denoiser import Denoiser

OPSET = 17
INPUTS = ("t", "x_t", "x0")
OUTPUT = "x0_hat"


def _require(module: str):
    try:
        return __import__(module)
    except ImportError:
        raise ValueError(f"the onnxruntime backend needs the '{module}' package: pip install {module} "
                         "(make install brings it)") from None


def export_bytes(net: Denoiser) -> bytes:
    """The network as an ONNX model (float32 weights), with a dynamic batch."""
    _require("onnx")
    cfg = net.cfg
    example = (torch.tensor([1, 2]), torch.zeros(2, cfg.frames, cfg.state_dim), torch.zeros(2, cfg.state_dim))
    names = list(INPUTS)
    if cfg.latent:
        example, names = (*example, torch.zeros(2, cfg.latent)), [*names, "z"]
    buf = io.BytesIO()
    was = net.training
    net.eval()
    try:
        with torch.no_grad(), warnings.catch_warnings():
            # the TorchScript exporter (no onnxscript needed) is deprecated upstream and warns
            # about the fixed q/k/v split; the parity test checks what it writes
            warnings.simplefilter("ignore")
            torch.onnx.export(net, example, buf, dynamo=False, opset_version=OPSET, input_names=names,
                              output_names=[OUTPUT], dynamic_axes={k: {0: "batch"} for k in (*names, OUTPUT)})
    finally:
        net.train(was)
    return buf.getvalue()


def _int8_pairs_saturate() -> bool:
    """Whether ONNX Runtime's uint8 x int8 MatMul on this CPU sums pairs of products in int16 and
    saturates (x86 without VNNI: AVX2's vpmaddubsw): 255 x 127 x 2 does not fit, 255 x 63 x 2
    does. Measured on an AVX2-only EPYC, shipped base, batch of 16: 8-bit weights 0.14 of the
    output's RMS off the float32 graph, 7-bit 0.025 (with VNNI, 8-bit 0.012). Unknown x86 flags
    count as saturating; other CPUs (ARM) as not."""
    import platform
    if platform.machine().lower() not in ("x86_64", "amd64", "i386", "i686"):
        return False
    try:
        flags = Path("/proc/cpuinfo").read_text()
    except OSError:
        return True
    return not any(f in flags.split() for f in ("avx512_vnni", "avx_vnni"))


def quantize_int8(model: bytes, reduce_range: bool | None = None) -> bytes:
    """The graph with its MatMul weights as int8, one scale per output channel, except the last
    MatMul (the output projection), which stays float32: it halves the error at no cost in time.
    The activations entering each int8 MatMul are quantized per row (every token of every
    avatar on its own scale, `_per_row_activations`), so an avatar's result does not depend on
    the others in its batch, as in float32 (docs/onnx.md). reduce_range: weights on 7 bits
    (None: where this CPU's int8 kernels would saturate with 8, `_int8_pairs_saturate`)."""
    if reduce_range is None:
        reduce_range = _int8_pairs_saturate()
    _require("onnxruntime")
    import tempfile

    import onnx
    from onnxruntime.quantization import QuantType, quantize_dynamic
    last = [n.name for n in onnx.load_from_string(model).graph.node if n.op_type == "MatMul"][-1:]  # nodes are in order
    # its advice to run shape inference first is for models with unknown shapes, not this one
    hint = _DropMessage("pre-processing before quantization")
    logging.getLogger().addFilter(hint)
    try:
        with tempfile.TemporaryDirectory() as d:
            src, dst = Path(d) / "float32.onnx", Path(d) / "int8.onnx"
            src.write_bytes(model)
            quantize_dynamic(src, dst, weight_type=QuantType.QInt8, per_channel=True, nodes_to_exclude=last,
                             reduce_range=reduce_range)
            return _per_row_activations(dst.read_bytes())
    finally:
        logging.getLogger().removeFilter(hint)


def _per_row_activations(model: bytes) -> bytes:
    """ONNX Runtime's dynamic quantization takes one scale for a whole activation tensor, the
    whole batch: one avatar's motion then changed with the others beside it (the crowd's rows
    must be independent: tests/test_runtime.py). Each DynamicQuantizeLinear is replaced by a
    symmetric quantization of every row (last axis) on its own scale max|x| / 127, stored as
    uint8 around the zero point 128; the MatMul's scale product takes 1 for it and the row
    scales multiply its float output, before any bias (so ONNX Runtime still fuses the integer
    MatMul with its weight scales)."""
    import onnx
    from onnx import TensorProto, helper

    m = onnx.load_from_string(model)
    g = m.graph
    consumers: dict[str, list] = {}
    for n in g.node:
        for x in n.input:
            consumers.setdefault(x, []).append(n)
    g.initializer.extend([helper.make_tensor("row_q/127", TensorProto.FLOAT, [], [127.0]),
                          helper.make_tensor("row_q/-127", TensorProto.FLOAT, [], [-127.0]),
                          helper.make_tensor("row_q/128", TensorProto.FLOAT, [], [128.0]),
                          helper.make_tensor("row_q/eps", TensorProto.FLOAT, [], [1e-8]),
                          helper.make_tensor("row_q/1", TensorProto.FLOAT, [], [1.0]),
                          helper.make_tensor("row_q/zero_point", TensorProto.UINT8, [], [128])])
    nodes, rescale = [], {}  # rescale: a scale-product Mul's output -> the row scales to apply after it
    for n in g.node:
        if n.op_type != "DynamicQuantizeLinear":
            nodes.append(n)
            continue
        x, (q, scale, zero) = n.input[0], n.output
        p = f"row_q/{n.name or x}/"
        nodes += [helper.make_node("Abs", [x], [p + "abs"]),
                  helper.make_node("ReduceMax", [p + "abs"], [p + "max"], axes=[-1], keepdims=1),
                  helper.make_node("Max", [p + "max", "row_q/eps"], [p + "range"]),
                  helper.make_node("Div", [p + "range", "row_q/127"], [scale]),
                  helper.make_node("Div", [x, scale], [p + "scaled"]),
                  helper.make_node("Round", [p + "scaled"], [p + "rounded"]),
                  helper.make_node("Clip", [p + "rounded", "row_q/-127", "row_q/127"], [p + "clipped"]),
                  helper.make_node("Add", [p + "clipped", "row_q/128"], [p + "shifted"]),
                  helper.make_node("Cast", [p + "shifted"], [q], to=TensorProto.UINT8),
                  helper.make_node("Identity", ["row_q/zero_point"], [zero])]
        for product in consumers[scale]:  # Mul(activation scale, weight scales)
            if product.op_type != "Mul" or any(c.op_type != "Mul" for c in consumers[product.output[0]]):
                raise ValueError(f"unexpected quantized graph around {n.name}: update _per_row_activations")
            product.input[list(product.input).index(scale)] = "row_q/1"
            for out in consumers[product.output[0]]:  # Mul(integer MatMul as float, scales)
                rescale[out.output[0]] = scale
    final = []
    for n in nodes:
        final.append(n)
        for k, out in enumerate(n.output):
            if out in rescale:
                n.output[k] = out + "/per_tensor"
                final.append(helper.make_node("Mul", [out + "/per_tensor", rescale[out]], [out]))
    del g.node[:]
    g.node.extend(final)
    return m.SerializeToString()


class _DropMessage(logging.Filter):
    def __init__(self, text: str):
        super().__init__()
        self.text = text

    def filter(self, record: logging.LogRecord) -> bool:
        return self.text not in record.getMessage()


def export_file(net: Denoiser, path: str | Path, int8: bool = False) -> Path:
    data = export_bytes(net)
    if int8:
        data = quantize_int8(data)
    return write_file(path, lambda tmp: Path(tmp).write_bytes(data))


class OnnxDenoiser:
    """Calls like Denoiser.forward(t, x_t, x0) -> x0_hat, run by an ONNX Runtime session."""

    def __init__(self, model: bytes | str | Path, threads: int | None = None):
        ort = _require("onnxruntime")
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads or torch.get_num_threads()
        opts.inter_op_num_threads = 1
        # no busy-waiting between calls: its worker threads would take the CPU the server's clock,
        # sockets and other sessions need (a flood test on one core fell to 15 fps beside them)
        opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
        src = model if isinstance(model, bytes) else str(model)
        self.session = ort.InferenceSession(src, opts, providers=["CPUExecutionProvider"])

    def __call__(self, t: torch.Tensor, x_t: torch.Tensor, x0: torch.Tensor, z: torch.Tensor | None = None) -> torch.Tensor:
        feed = {"t": t.long().numpy(), "x_t": np.ascontiguousarray(x_t.float().numpy()),
                "x0": np.ascontiguousarray(x0.float().numpy())}
        if z is not None:
            feed["z"] = np.ascontiguousarray(z.float().numpy())
        return torch.from_numpy(self.session.run([OUTPUT], feed)[0])


_SESSIONS: "weakref.WeakKeyDictionary[Denoiser, dict[bool, OnnxDenoiser]]" = weakref.WeakKeyDictionary()


def onnx_denoiser(net: Denoiser, int8: bool = False) -> OnnxDenoiser:
    """The network exported in memory (with int8 weights: quantize_int8) and loaded into ONNX
    Runtime (about a second, two with int8), once per network object and precision: a runtime's
    network is frozen (a network whose weights change after this call keeps its old session)."""
    sessions = _SESSIONS.setdefault(net, {})
    if int8 not in sessions:
        data = export_bytes(net)
        sessions[int8] = OnnxDenoiser(quantize_int8(data) if int8 else data)
    return sessions[int8]
