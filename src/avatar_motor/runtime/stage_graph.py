"""The post-processing stages (runtime/stages.py) traced into one TorchScript graph, what
`RuntimeConfig.trace_stages` runs: for one avatar the stages are some 1,400 small tensor
operations, each of which costs more to dispatch from Python than to compute. The graph runs the
same kernels on the same values, so its output is bit for bit the Python stages' (the tests
check it), in about 0.6x their time at one avatar. Small batches run the graph frozen, in
TorchScript's static runtime (`_Graph`), which dispatches each of its ~1,000 operations with less
overhead than the graph interpreter: 0.17-0.19 ms less at 1-16 avatars (1 avatar: 0.89 against
1.04 ms), the same values bit for bit.

A graph is traced for one signature: the runtime config (the stages and their settings), the
dtype, the frames of the segment and of the past, and whether some body has a facing goal
(turn_toward runs or not). The batch size is free. Each is traced once per process (0.1 s) and
kept. The stages read no Python value off the batch's tensors (StageContext), so that one trace
fits every batch of its signature.

Exported to ONNX Runtime instead, the same stages ran at about 0.75-0.9x the Python's time at one
avatar (some 2,000 nodes at about a microsecond each) and differed from it by up to 1e-4 m."""
from __future__ import annotations

import logging
import threading
import warnings

import torch

from .stages import StageContext, run_stages


class _Stages(torch.nn.Module):
    def __init__(self, cfg, any_facing: bool):
        super().__init__()
        self.cfg, self.any_facing = cfg, any_facing

    def forward(self, seg, x0, offsets, steered, facing, has_facing, lock_where, lock_yaw, match_velocity,
                past=None, has_past=None):
        ctx = StageContext(x0, offsets, steered, facing, has_facing, lock_where, lock_yaw, match_velocity, past,
                           has_past, any_facing=self.any_facing)
        return run_stages(self.cfg, ctx, seg)


def _tensors(ctx: StageContext, seg: torch.Tensor) -> tuple[torch.Tensor, ...]:
    out = (seg, ctx.x0, ctx.offsets, ctx.steered, ctx.facing, ctx.has_facing, ctx.lock_where, ctx.lock_yaw,
           ctx.match_velocity)
    return out + ((ctx.past, ctx.has_past) if ctx.past is not None else ())


def signature(cfg, ctx: StageContext, seg: torch.Tensor) -> tuple:
    """What a traced graph is fixed to (the batch size is not)."""
    return (repr(cfg), seg.dtype, seg.shape[1], None if ctx.past is None else ctx.past.shape[1], ctx.any_facing)


log = logging.getLogger("avatar_motor.runtime")


# the largest batch the static runtime runs: it holds Python's lock for the whole call (the
# interpreter lets go of it), and the server's clock and sockets wait meanwhile: with 128 avatars
# a 1-ms sleep beside it took 39 ms instead of 1.1; 4 avatars hold it for about 1.6 ms
STATIC_ROWS = 4


class _Graph:
    """A traced graph, run by TorchScript's static runtime (torch._C's StaticModule, what PyTorch
    offers for small-batch CPU inference: the same kernels, their outputs' memory planned once)
    for batches of up to STATIC_ROWS rows, by its interpreter for larger ones. The static runtime
    keeps that memory per graph, so its calls from the server's threads take turns."""

    def __init__(self, traced: torch.jit.ScriptModule):
        self.traced = traced
        try:
            self.static = torch._C._jit_to_static_module(torch.jit.freeze(traced.eval())._c)
        except RuntimeError as e:  # an operation it has no form for: the interpreter runs every batch
            log.warning("post-processing runs in TorchScript's interpreter, not its static runtime: %s", e)
            self.static = None
        self.lock = threading.Lock()

    def __call__(self, seg: torch.Tensor, *rest: torch.Tensor) -> torch.Tensor:
        if self.static is None or len(seg) > STATIC_ROWS:
            return self.traced(seg, *rest)
        with self.lock:
            return self.static(seg, *rest)


_GRAPHS: dict[tuple, _Graph] = {}
_LOCK = threading.Lock()


def trace_stages(cfg, ctx: StageContext, seg: torch.Tensor) -> _Graph:
    """The graph of run_stages for the signature of (cfg, ctx, seg), traced on them."""
    with torch.no_grad(), warnings.catch_warnings():
        # the tracer warns of every constant it records (index lists, the config's numbers);
        # tests/test_runtime.py checks the graph against the Python stages on other batches
        warnings.simplefilter("ignore")
        return _Graph(torch.jit.trace(_Stages(cfg, ctx.any_facing), _tensors(ctx, seg), check_trace=False))


def run_traced_stages(cfg, ctx: StageContext, seg: torch.Tensor) -> torch.Tensor:
    """run_stages(cfg, ctx, seg) through the traced graph of its signature (traced at first use)."""
    key = signature(cfg, ctx, seg)
    with _LOCK:  # the server's threads trace a signature once
        graph = _GRAPHS.get(key)
        if graph is None:
            graph = _GRAPHS[key] = trace_stages(cfg, ctx, seg)
    return graph(*_tensors(ctx, seg))
