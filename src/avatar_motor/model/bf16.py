"""The denoiser with the weights of its linear layers in bfloat16, traced into a TorchScript graph:
what the runtime runs for batches smaller than `RuntimeConfig.bfloat16_from` on a CPU with
bfloat16 matrix units (runtime/sampler.BatchSwitch). Each linear layer casts its input to
bfloat16 and its output back to float32; normalisation, attention's products and the rest stay in
float32. At one avatar a call took 0.68x ONNX Runtime's float32 time (1.8 vs 2.6 ms, interleaved)
where autocast, which casts the weights again at every call, took as long as float32. For large
batches autocast is faster (its attention is in bfloat16 too): 256 rows 118 against 198 ms."""
from __future__ import annotations

import copy
import warnings
import weakref

import torch
import torch.nn.functional as F

from .denoiser import Denoiser


class _Bf16Linear(torch.nn.Module):
    def __init__(self, lin: torch.nn.Linear):
        super().__init__()
        self.register_buffer("weight", lin.weight.detach().to(torch.bfloat16))
        self.register_buffer("bias", None if lin.bias is None else lin.bias.detach().to(torch.bfloat16))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.linear(x.to(torch.bfloat16), self.weight, self.bias).float()


def _swap_linears(m: torch.nn.Module) -> None:
    for name, child in m.named_children():
        if isinstance(child, torch.nn.Linear):
            setattr(m, name, _Bf16Linear(child))
        else:
            _swap_linears(child)


_GRAPHS: "weakref.WeakKeyDictionary[Denoiser, torch.jit.ScriptModule]" = weakref.WeakKeyDictionary()


def bf16_denoiser(net: Denoiser) -> torch.jit.ScriptModule:
    """net(t, x_t, x0[, z]) with bfloat16 linear weights, traced (the batch size is free); made
    once per network object (a network whose weights change afterwards keeps its old graph)."""
    if net not in _GRAPHS:
        if net.cfg.persona:
            raise ValueError("bf16_denoiser takes a network without persona conditions")
        m = copy.deepcopy(net).eval()
        _swap_linears(m)
        cfg = net.cfg
        example = (torch.tensor([1, 2]), torch.zeros(2, cfg.frames, cfg.state_dim), torch.zeros(2, cfg.state_dim))
        if cfg.latent:
            example = (*example, torch.zeros(2, cfg.latent))
        with torch.inference_mode(False), torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the tracer's notes on constants; the test checks other batch sizes
            _GRAPHS[net] = torch.jit.trace(m, example, check_trace=False)
    return _GRAPHS[net]
