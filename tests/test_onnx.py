"""The ONNX Runtime backend: the exported graph computes the network, and the runtime on it
generates the same motion as on torch."""
import numpy as np
import pytest
import torch

from avatar_motor.model.onnx import OnnxDenoiser, export_file, onnx_denoiser
from avatar_motor.runtime.crowd import Crowd, RuntimeConfig

from .conftest_models import shipped_or_tiny

pytest.importorskip("onnxruntime")


def test_the_exported_network_matches_torch_for_any_batch(tmp_path):
    motor = shipped_or_tiny(tmp_path)
    net = motor.net
    path = export_file(net, tmp_path / "denoiser.onnx")
    ort_net = OnnxDenoiser(path)
    g = torch.Generator().manual_seed(0)
    cfg = net.cfg
    for B in (1, 3, 17):
        t = torch.randint(0, motor.diffusion.T, (B,), generator=g)
        x_t, x0 = torch.randn(B, cfg.frames, cfg.state_dim, generator=g), torch.randn(B, cfg.state_dim, generator=g)
        with torch.inference_mode():
            ref = net(t, x_t, x0)
        out = ort_net(t, x_t, x0)
        assert out.shape == ref.shape and out.dtype == torch.float32
        assert float((out - ref).abs().max()) <= 1e-4
    assert onnx_denoiser(net) is onnx_denoiser(net)  # exported once per network


def test_the_runtime_on_onnxruntime_makes_the_same_motion(tmp_path):
    motor = shipped_or_tiny(tmp_path)
    out = {}
    for backend in ("torch", "onnxruntime"):
        crowd = Crowd(motor, RuntimeConfig(backend=backend), seed=3)
        i = crowd.spawn()
        crowd.set_goal(i, (1.0, 0.2))
        out[backend] = torch.stack([crowd.step_segment()[i] for _ in range(2)])
    d = (out["torch"] - out["onnxruntime"]).abs()
    print(f"torch vs onnxruntime, two segments: max {float(d.max()):.2e}")
    assert float(d.max()) < 1e-3  # float32 arithmetic in another order, through 8 denoising steps
    with pytest.raises(ValueError, match="backend must be one of"):
        Crowd(motor, RuntimeConfig(backend="tensorrt"))
