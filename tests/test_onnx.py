"""The ONNX Runtime backend: the exported graph computes the network, and the runtime on it
generates the same motion as on torch."""
import pytest
import torch

from avatar_motor.model.onnx import OnnxDenoiser, export_bytes, export_file, onnx_denoiser, quantize_int8
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
        crowd = Crowd(motor, RuntimeConfig(backend=backend, int8_weights=False), seed=3)
        i = crowd.spawn()
        crowd.set_goal(i, (1.0, 0.2))
        out[backend] = torch.stack([crowd.step_segment()[i] for _ in range(2)])
    d = (out["torch"] - out["onnxruntime"]).abs()
    print(f"torch vs onnxruntime, two segments: max {float(d.max()):.2e}")
    assert float(d.max()) < 1e-3  # float32 arithmetic in another order, through 8 denoising steps
    with pytest.raises(ValueError, match="backend must be one of"):
        Crowd(motor, RuntimeConfig(backend="tensorrt"))


def test_int8_weights_make_a_smaller_graph_that_computes_nearly_the_same(tmp_path):
    """The runtime's default graph: MatMul weights as int8. Its output stays within a few percent
    of the float32 graph's (measured quality: docs/onnx.md), with the same inputs and output."""
    motor = shipped_or_tiny(tmp_path)
    net, cfg = motor.net, motor.net.cfg
    f32 = export_bytes(net)
    i8 = quantize_int8(f32)
    assert len(i8) < 0.5 * len(f32)
    import onnx
    ops = [n.op_type for n in onnx.load_from_string(i8).graph.node if "MatMul" in n.op_type]
    assert "MatMulInteger" in ops and ops[-1] == "MatMul"  # the output projection stays float32
    a, b = OnnxDenoiser(f32), OnnxDenoiser(i8)
    assert [i.name for i in a.session.get_inputs()] == [i.name for i in b.session.get_inputs()]
    g = torch.Generator().manual_seed(1)
    B = 16
    args = (torch.randint(0, motor.diffusion.T, (B,), generator=g), torch.randn(B, cfg.frames, cfg.state_dim, generator=g),
            torch.randn(B, cfg.state_dim, generator=g))
    if cfg.latent:
        args = (*args, torch.randn(B, cfg.latent, generator=g))
    ref, out = a(*args), b(*args)
    rel = float((out - ref).abs().mean() / ref.pow(2).mean().sqrt())
    print(f"int8 vs float32 weights: mean absolute error {rel:.3f} of the output's RMS")
    assert 0 < rel < 0.1
    # 7-bit weights, which the CPUs whose int8 kernels saturate get (model/onnx._int8_pairs_saturate;
    # 8-bit read 0.14-0.16 on an AVX2-only EPYC): near on any CPU
    seven = OnnxDenoiser(quantize_int8(f32, reduce_range=True))(*args)
    assert float((seven - ref).abs().mean() / ref.pow(2).mean().sqrt()) < 0.1
    assert torch.equal(out, b(*args))  # deterministic
    # each row on its own activation scales: an avatar's result does not depend on its batch
    alone = b(*(a[3:4] for a in args))
    assert torch.equal(alone[0], out[3])
    assert onnx_denoiser(net, True) is onnx_denoiser(net, True) and onnx_denoiser(net, True) is not onnx_denoiser(net)
    from avatar_motor.cli import main
    assert main(["export-onnx", "--model", str(motor.path), "--int8", "--out", str(tmp_path / "q.onnx")]) == 0
    assert (tmp_path / "q.onnx").read_bytes() == i8


def test_the_runtime_on_int8_weights_repeats_itself_per_seed(tmp_path):
    motor = shipped_or_tiny(tmp_path)
    assert RuntimeConfig().backend == "onnxruntime" and not RuntimeConfig().int8_weights  # float32 by default
    runs = []
    for _ in range(2):
        crowd = Crowd(motor, RuntimeConfig(int8_weights=True), seed=5)
        i = crowd.spawn()
        crowd.set_goal(i, (1.0, 0.0))
        runs.append(torch.stack([crowd.step_segment()[i] for _ in range(2)]))
    assert torch.equal(runs[0], runs[1])
    net = crowd.sampler.net
    assert getattr(net, "small", net) is onnx_denoiser(motor.net, True)  # int8 asked for: kept for one avatar


def test_large_batches_run_the_network_in_bfloat16_and_repeat_themselves(tmp_path):
    from avatar_motor.runtime.sampler import BatchSwitch, bfloat16_units
    motor = shipped_or_tiny(tmp_path)
    net = motor.net.eval()
    calls = []
    switch = BatchSwitch(lambda *a: calls.append(len(a[1])) or net(*a), net, rows=4)
    cfg = net.cfg
    g = torch.Generator().manual_seed(0)
    args = [torch.full((6,), 3), torch.randn(6, cfg.frames, cfg.state_dim, generator=g),
            torch.randn(6, cfg.state_dim, generator=g)] + ([torch.randn(6, cfg.latent, generator=g)] if cfg.latent else [])
    with torch.no_grad():
        small = switch(*[a[:3] for a in args])
        large = switch(*args)
        exact = net(*args)
    assert calls == [3]  # 3 rows went to the float32 network, 6 did not
    assert torch.allclose(small, exact[:3], atol=1e-5)
    assert large.dtype == torch.float32 and not torch.equal(large, exact)  # computed in bfloat16 ...
    assert float((large - exact).abs().max()) < 0.1 * float(exact.abs().max())  # ... close to float32
    if not bfloat16_units():
        return  # the runtime uses no bfloat16 on this CPU
    assert isinstance(Crowd(motor, RuntimeConfig(bfloat16_from=2)).sampler.net, BatchSwitch)
    runs = []
    for _ in range(2):  # a crowd above the threshold repeats itself per seed
        crowd = Crowd(motor, RuntimeConfig(bfloat16_from=2), seed=5)
        ids = [crowd.spawn(position=(k, 0.0)) for k in range(3)]
        crowd.set_goal(ids[0], (1.0, 0.0))
        runs.append(torch.stack([torch.stack([s[i] for i in ids]) for s in (crowd.step_segment() for _ in range(2))]))
    assert torch.equal(runs[0], runs[1])


def test_the_bfloat16_graph_takes_any_batch_and_stays_near_float32(tmp_path):
    """model/bf16.py: traced on a batch of 2, the graph gives what its module gives on batches of
    1 and 5, in float32 and near the float32 network."""
    import copy
    from avatar_motor.model.bf16 import _swap_linears, bf16_denoiser
    motor = shipped_or_tiny(tmp_path)
    net = motor.net.eval()
    graph = bf16_denoiser(net)
    assert bf16_denoiser(net) is graph  # made once per network
    module = copy.deepcopy(net)
    _swap_linears(module)
    cfg = net.cfg
    g = torch.Generator().manual_seed(1)
    for B in (1, 5):
        args = [torch.full((B,), 2), torch.randn(B, cfg.frames, cfg.state_dim, generator=g),
                torch.randn(B, cfg.state_dim, generator=g)] + ([torch.randn(B, cfg.latent, generator=g)] if cfg.latent else [])
        with torch.no_grad():
            out, exact = graph(*args), net(*args)
            assert out.dtype == torch.float32 and torch.equal(out, module(*args))
        assert 0 < float((out - exact).abs().max()) < 0.1 * float(exact.abs().max())
