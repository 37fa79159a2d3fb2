import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from avatar_motor.data.dataset import Normalizer
from avatar_motor.body.motion_state import STATE_DIM
from avatar_motor.model.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from avatar_motor.model.denoiser import Denoiser, DenoiserConfig
from avatar_motor.model.diffusion import Diffusion, cosine_betas

TINY = DenoiserConfig(width=32, depth=2, heads=4, ff=64, dropout=0.0)


def test_cosine_schedule_against_independent_formulas():
    T = 50
    # independent: alpha_bar from the closed form, betas from ratios, clipped at 0.999
    f = [math.cos((t / T + 0.008) / 1.008 * math.pi / 2) ** 2 for t in range(T + 1)]
    betas = [min(1 - f[t + 1] / f[t], 0.999) for t in range(T)]
    assert torch.allclose(cosine_betas(T), torch.tensor(betas, dtype=torch.float64), atol=1e-12)
    d = Diffusion(T)
    ab = 1.0
    for t in range(T):
        ab_prev, ab = ab, ab * (1 - betas[t])
        s = d.train
        assert s.alphas_cumprod[t].item() == pytest.approx(ab, rel=1e-9)
        # posterior q(x_{t-1} | x_t, x_0): DDPM Eq. 6-7
        assert s.posterior_mean_coef1[t].item() == pytest.approx(betas[t] * math.sqrt(ab_prev) / (1 - ab), rel=1e-9)
        assert s.posterior_mean_coef2[t].item() == pytest.approx((1 - ab_prev) * math.sqrt(1 - betas[t]) / (1 - ab), rel=1e-9)
        assert s.posterior_variance[t].item() == pytest.approx(betas[t] * (1 - ab_prev) / (1 - ab), rel=1e-9, abs=1e-15)
    assert s.posterior_variance[0].item() == 0.0


def test_respacing_keeps_alpha_bar_and_sampler_runs():
    d = Diffusion(50)
    for steps in (1, 10, 25, 50):
        s = d.respaced(steps)
        assert len(s.timesteps) == steps and int(s.timesteps[-1]) == 49  # every chain starts from pure noise
        assert torch.allclose(s.alphas_cumprod, d.train.alphas_cumprod[s.timesteps])
    with pytest.raises(ValueError, match="between 1 and 50"):
        d.respaced(51)
    # a perfect denoiser returns the clean sample whatever the noise
    target = torch.randn(3, 15, 8)
    for eta in (1.0, 0.0):
        out = d.sample(lambda x, t: target, target.shape, steps=10, generator=torch.Generator().manual_seed(0), eta=eta)
        assert torch.allclose(out, target)


def test_q_sample_statistics():
    d = Diffusion(50)
    x0 = torch.ones(20000, 1)
    t = torch.full((20000,), 25)
    xt = d.q_sample(x0, t, torch.randn(20000, 1, generator=torch.Generator().manual_seed(0)))
    ab = d.train.alphas_cumprod[25].item()
    assert xt.mean().item() == pytest.approx(math.sqrt(ab), abs=0.02)
    assert xt.var().item() == pytest.approx(1 - ab, abs=0.02)


@pytest.mark.parametrize("arch", ["incontext", "adaln"])
def test_denoiser_shapes(arch):
    net = Denoiser(DenoiserConfig(arch=arch, width=32, depth=2, heads=4, ff=64))
    out = net(torch.tensor([0, 49]), torch.randn(2, 15, STATE_DIM), torch.randn(2, STATE_DIM))
    assert out.shape == (2, 15, STATE_DIM)


def test_fk_loss_gradients_are_correct():
    from avatar_motor.body.skeleton import SHAPE_DIM
    from avatar_motor.train.losses import fk_joints
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2, 3, STATE_DIM, generator=g, dtype=torch.float64, requires_grad=True)
    shapes = torch.randn(2, SHAPE_DIM, generator=g, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda x: fk_joints(x, shapes), (x,), eps=1e-6, atol=1e-5)


def _tiny_norm():
    return Normalizer(torch.zeros(STATE_DIM), torch.ones(STATE_DIM))


def test_checkpoint_roundtrip_and_errors(tmp_path):
    net = Denoiser(TINY)
    save_checkpoint(tmp_path / "ck", net, _tiny_norm(), {"name": "tiny", "licence": "test"}, "# tiny\n")
    m = load_checkpoint(tmp_path / "ck")
    for k, v in net.state_dict().items():
        assert torch.equal(m.net.state_dict()[k], v)
    assert m.name == "tiny"
    # corrupt weights
    bad = tmp_path / "bad"
    save_checkpoint(bad, net, _tiny_norm())
    (bad / "model.safetensors").write_bytes(b"\x00" * 64)
    with pytest.raises(CheckpointError, match="corrupt or truncated"):
        load_checkpoint(bad)
    # mismatched architecture
    mis = tmp_path / "mis"
    save_checkpoint(mis, net, _tiny_norm())
    cfg = json.loads((mis / "config.json").read_text())
    cfg["denoiser"]["depth"] = 3
    (mis / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(CheckpointError, match="missing"):
        load_checkpoint(mis)
    cfg["denoiser"]["depth"] = 2
    cfg["denoiser"]["width"] = 64
    (mis / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(CheckpointError, match="shape mismatch"):
        load_checkpoint(mis)
    with pytest.raises(CheckpointError, match="no such checkpoint"):
        load_checkpoint(tmp_path / "nothing")
    (mis / "config.json").write_text("{not json")
    with pytest.raises(CheckpointError, match="not valid JSON"):
        load_checkpoint(mis)
    # every field checked before anything is allocated (a 1e6-frame network would take gigabytes)
    good = json.loads((tmp_path / "ck" / "config.json").read_text())
    for change, message in ((lambda c: [c], "JSON object"), (lambda c: {**c, "denoiser": [1]}, "object of fields"),
                            (lambda c: {**c, "denoiser": {**c["denoiser"], "heads": 7}}, "multiple of 'heads'"),
                            (lambda c: {**c, "denoiser": {**c["denoiser"], "frames": 1e6}}, "'frames' must be an integer"),
                            (lambda c: {**c, "denoiser": {**c["denoiser"], "width": 4096, "depth": 64}}, "beyond what"),
                            (lambda c: {**c, "denoiser": {**c["denoiser"], "dropout": "x"}}, "'dropout'"),
                            (lambda c: {**c, "denoiser": {**c["denoiser"], "wings": 2}}, "unknown denoiser fields"),
                            (lambda c: {**c, "diffusion": {"train_steps": -5}}, "train_steps"),
                            (lambda c: {**c, "normalizer": {"mean": [float("nan")] * len(c["normalizer"]["mean"]),
                                                            "std": c["normalizer"]["std"]}}, "finite means")):
        (mis / "config.json").write_text(json.dumps(change(good)))
        with pytest.raises(CheckpointError, match=message):
            load_checkpoint(mis)


@pytest.fixture
def fixture_cache(tmp_path):
    from avatar_motor.data.cache import import_motion
    from .fixture_tools import FIXTURES
    path, _ = import_motion(FIXTURES, name="fixtures", progress=False, workers=1)
    return path


def _cfg(out, cache, **kw):
    from avatar_motor.data.dataset import SegmentConfig
    from avatar_motor.train.trainer import TrainConfig
    d = dict(data=[str(cache)], out=str(out), steps=6, batch=8, lr=1e-3, checkpoint_every=3, log_every=1,
             ema_start=2, model=TINY, segment=SegmentConfig(split="all"))
    d.update(kw)
    return TrainConfig(**d)


def test_tiny_model_overfits(tmp_path, fixture_cache):
    from avatar_motor.data.dataset import SegmentConfig
    from avatar_motor.train.trainer import Trainer
    cfg = _cfg(tmp_path / "run", fixture_cache, steps=400, lr=3e-3, batch=8, checkpoint_every=1000,
               segment=SegmentConfig(split="all", shape_augment=0.0, mirror=False),
               model=DenoiserConfig(width=64, depth=2, heads=4, ff=128, dropout=0.0))
    tr = Trainer(cfg, progress=False)
    tr.ds.window_starts = tr.ds.window_starts[:4]  # a dataset of four windows to memorize
    h = tr.run()
    first = sum(m["loss"] for m in h[:10]) / 10
    last = sum(m["loss"] for m in h[-10:]) / 10
    assert last < first / 10, (first, last)


def test_resume_is_exact(tmp_path, fixture_cache):
    from avatar_motor.train.trainer import Trainer
    full = Trainer(_cfg(tmp_path / "a", fixture_cache), progress=False).run()
    part = Trainer(_cfg(tmp_path / "b", fixture_cache, steps=3), progress=False)
    part.run()
    rest = Trainer(_cfg(tmp_path / "b", fixture_cache), progress=False)
    assert rest.step == 3
    resumed = rest.run()
    assert [m["loss"] for m in full[3:]] == pytest.approx([m["loss"] for m in resumed], rel=1e-6)
    ck = load_checkpoint(tmp_path / "b" / "checkpoint")
    assert ck.config["trained_steps"] == 6 and "non-commercial" in ck.config["licence"]
    assert (tmp_path / "b" / "loss.png").exists() and (tmp_path / "b" / "metrics.jsonl").exists()


def test_a_checkpoint_before_the_first_logged_step_is_saved(tmp_path, fixture_cache):
    from avatar_motor.train.trainer import Trainer
    # found by a smoke run of `make models` with small budgets: the loss plot read a log not yet written
    Trainer(_cfg(tmp_path / "a", fixture_cache, steps=3, checkpoint_every=1, log_every=25), progress=False).run()
    assert load_checkpoint(tmp_path / "a" / "checkpoint").config["trained_steps"] == 3
    assert len((tmp_path / "a" / "metrics.jsonl").read_text().splitlines()) == 1  # the last step's line


def test_warm_start_takes_the_weights_and_checks_the_architecture(tmp_path, fixture_cache):
    from avatar_motor.train.trainer import Trainer
    Trainer(_cfg(tmp_path / "a", fixture_cache, steps=3), progress=False).run()
    src = load_checkpoint(tmp_path / "a" / "checkpoint")
    warm = Trainer(_cfg(tmp_path / "b", fixture_cache, init=str(tmp_path / "a" / "checkpoint")), progress=False)
    assert warm.step == 0
    for k, v in src.net.state_dict().items():
        assert torch.equal(warm.net.state_dict()[k], v) and torch.equal(warm.ema.shadow[k], v)
    with pytest.raises(ValueError, match="same architecture"):
        Trainer(_cfg(tmp_path / "c", fixture_cache, init=str(tmp_path / "a" / "checkpoint"),
                     model=DenoiserConfig(width=32, depth=1, heads=2, ff=64)), progress=False)


def test_stop_at_ends_a_run_early_on_the_planned_schedule_and_init_stats_keeps_the_init_normalisation(tmp_path, fixture_cache):
    from avatar_motor.data.dataset import SegmentConfig
    from avatar_motor.train.trainer import Trainer
    full = Trainer(_cfg(tmp_path / "a", fixture_cache, warmup=1, lr_final_ratio=0.1), progress=False)
    stopped = Trainer(_cfg(tmp_path / "b", fixture_cache, warmup=1, lr_final_ratio=0.1, stop_at=4), progress=False)
    h_full, h_stop = full.run(), stopped.run()
    assert stopped.step == 4 and [m["loss"] for m in h_stop] == pytest.approx([m["loss"] for m in h_full[:4]], rel=1e-6)
    assert stopped.lr_at(3) == full.lr_at(3) > full.lr_at(5)  # the 6-step cosine, not a 4-step one
    # continuing on other data with the init's normalisation (not the new data's)
    init = str(tmp_path / "a" / "checkpoint")
    kept = Trainer(_cfg(tmp_path / "c", fixture_cache, init=init, init_stats=True,
                        segment=SegmentConfig(split="all", shape_augment=2.0)), progress=False)
    assert torch.equal(kept.norm.mean, load_checkpoint(init).norm.mean)
    with pytest.raises(ValueError, match="set init"):
        Trainer(_cfg(tmp_path / "d", fixture_cache, init_stats=True), progress=False)


def test_normalisation_statistics_follow_a_reimported_cache(tmp_path, fixture_cache):
    from avatar_motor.data.cache import MotionCache
    from avatar_motor.data.dataset import SegmentConfig, SegmentDataset, load_or_compute_stats, stats_path
    ds = SegmentDataset([MotionCache.load(fixture_cache)], SegmentConfig(split="all"))
    first = load_or_compute_stats(ds, [fixture_cache])
    p = stats_path([fixture_cache])
    doctored = json.loads(p.read_text())
    doctored["mean"] = [0.0] * len(doctored["mean"])
    p.write_text(json.dumps(doctored))
    assert float(load_or_compute_stats(ds, [fixture_cache]).mean.abs().max()) == 0  # same cache: the file is used
    st = fixture_cache.stat()
    os.utime(fixture_cache, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))  # the cache was written again
    assert torch.equal(load_or_compute_stats(ds, [fixture_cache]).mean, first.mean)


def test_ddp_two_processes_equal_one_with_double_batch(tmp_path, fixture_cache):
    """2 gloo processes with batch 8 each (global 16) take the same steps as 1 process with 16."""
    script = tmp_path / "run.py"
    script.write_text(f"""
import json, sys, torch
sys.path.insert(0, {str(Path(__file__).parents[1])!r})
from tests.test_model import _cfg
from avatar_motor.train.trainer import Trainer
out = sys.argv[1]
tr = Trainer(_cfg(out, {str(fixture_cache)!r}, batch=16, steps=3), progress=False)
h = tr.run()
if tr.rank == 0:
    json.dump([m["loss"] for m in h], open(out + ".json", "w"))
    torch.save({{k: v for k, v in tr.net.state_dict().items()}}, out + ".pt")
""")
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    subprocess.run([sys.executable, str(script), str(tmp_path / "one")], check=True, env=env)
    import socket
    with socket.socket() as s:  # a free port: a fixed one can be taken on a shared machine
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    r = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--nproc_per_node=2", f"--master_port={port}",
                        str(script), str(tmp_path / "two")], env=env, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-4000:]  # the workers' own error, not just an exit status
    l1 = json.loads((tmp_path / "one.json").read_text())
    l2 = json.loads((tmp_path / "two.json").read_text())
    assert l1 == pytest.approx(l2, rel=1e-5)
    # the trained networks compute the same function (parameters the loss cannot see, such as the
    # attention key bias, get float-noise gradients that Adam magnifies; they don't change outputs)
    nets = []
    for name in ("one", "two"):
        net = Denoiser(TINY)
        net.load_state_dict(torch.load(tmp_path / f"{name}.pt"))
        nets.append(net.eval())
    g = torch.Generator().manual_seed(0)
    x, x0 = torch.randn(4, 15, STATE_DIM, generator=g), torch.randn(4, STATE_DIM, generator=g)
    t = torch.tensor([0, 10, 30, 49])
    assert torch.allclose(nets[0](t, x, x0), nets[1](t, x, x0), atol=1e-4)


class _Killed(BaseException):
    """A simulated kill -9: nothing after it runs (not even except Exception handlers)."""


def _kill_at(monkeypatch, k: int) -> list:
    """Make the k-th file operation of a save (renames, removals, writes) never happen: the
    process 'dies' just before it. Returns the list of operations seen."""
    import shutil
    from pathlib import Path

    import avatar_motor.model.checkpoint as ckpt
    import avatar_motor.train.trainer as trainer
    seen = []

    def wrap(name, fn):
        def op(*a, **kw):
            seen.append(name)
            if len(seen) == k:
                raise _Killed(name)
            return fn(*a, **kw)
        return op

    monkeypatch.setattr(Path, "rename", wrap("rename", Path.rename))
    monkeypatch.setattr(Path, "write_text", wrap("write_text", Path.write_text))
    monkeypatch.setattr(Path, "mkdir", wrap("mkdir", Path.mkdir))
    monkeypatch.setattr(shutil, "rmtree", wrap("rmtree", shutil.rmtree))
    monkeypatch.setattr(ckpt, "save_file", wrap("save_file", ckpt.save_file))
    monkeypatch.setattr(trainer, "save_file", wrap("save_file", trainer.save_file))
    return seen


def test_a_kill_at_any_instant_of_a_save_leaves_a_state_that_resumes_exactly(tmp_path, fixture_cache, monkeypatch):
    # dropout 0.1: resume is exact only if the saved random state is the one training goes on with
    from avatar_motor.train.trainer import Trainer
    cfg = dict(model=DenoiserConfig(width=32, depth=2, heads=4, ff=64, dropout=0.1), steps=6, checkpoint_every=3)
    full = Trainer(_cfg(tmp_path / "full", fixture_cache, **cfg), progress=False)
    full.run()
    reference = {k: v.clone() for k, v in full.net.state_dict().items()}
    k = 1
    while True:  # kill the second save (at step 6, over the first one's state) at its k-th file operation
        out = tmp_path / f"k{k}"
        Trainer(_cfg(out, fixture_cache, **cfg), progress=False).run(3)
        t = Trainer(_cfg(out, fixture_cache, **cfg), progress=False)
        with monkeypatch.context() as m:
            seen = _kill_at(m, k)
            try:
                t.run()
                finished = True
            except _Killed:
                finished = False
        again = Trainer(_cfg(out, fixture_cache, **cfg), progress=False)  # the next run, after the kill
        assert again.step in (3, 6), f"kill at operation {k} ({seen[-1]}): resumed at step {again.step}"
        leftovers = sorted(p.name for p in out.iterdir() if p.name.endswith((".tmp", ".old")))
        assert leftovers == [], f"kill at operation {k}: stale {leftovers}"
        assert load_checkpoint(out / "checkpoint").config["trained_steps"] in (3, 6)
        again.run()
        for name, v in again.net.state_dict().items():
            assert torch.equal(v, reference[name]), f"kill at operation {k} ({seen[-1]}): {name} differs after resuming"
        steps = [json.loads(ln)["step"] for ln in (out / "metrics.jsonl").read_text().splitlines()]
        assert steps == sorted(set(steps)), f"kill at operation {k}: metric lines duplicated"
        if finished:
            break
        k += 1
    assert k > 8  # every step of both folder swaps was hit
