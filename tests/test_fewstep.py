"""Few-step samplers (model/fewstep.py, train/fewstep.py): the chains, the posterior step, the
discriminator, the latent generator, training with exact resume, and the runtime on them."""
import json
from pathlib import Path

import pytest
import torch

from avatar_motor.model.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from avatar_motor.model.denoiser import Denoiser, DenoiserConfig
from avatar_motor.model.diffusion import Diffusion
from avatar_motor.model.fewstep import (Discriminator, abar_at, forward_pair, posterior_coefficients,
                                        posterior_sample, sample, trailing_timesteps)
from avatar_motor.runtime.crowd import Crowd, RuntimeConfig

from .conftest_models import tiny_motor
from .test_model import fixture_cache  # noqa: F401 (a fixture)

TINY = dict(width=32, depth=2, heads=4, ff=64, dropout=0.0)


def test_trailing_chains_start_from_pure_noise():
    assert trailing_timesteps(50, 1).tolist() == [49]
    assert trailing_timesteps(50, 2).tolist() == [24, 49]
    assert trailing_timesteps(50, 4).tolist() == [11, 24, 37, 49]
    assert trailing_timesteps(50, 50).tolist() == list(range(50))
    with pytest.raises(ValueError):
        trailing_timesteps(50, 0)


def test_posterior_coefficients_match_the_respaced_chain_and_the_clean_end():
    d = Diffusion(50)
    s = d.respaced(8)
    for k in range(1, len(s.timesteps)):
        c1, c2, var = posterior_coefficients(s.alphas_cumprod[k], s.alphas_cumprod_prev[k])
        assert float(c1) == pytest.approx(float(s.posterior_mean_coef1[k]), rel=1e-12)
        assert float(c2) == pytest.approx(float(s.posterior_mean_coef2[k]), rel=1e-12)
        assert float(var) == pytest.approx(float(s.posterior_variance[k]), rel=1e-12)
    c1, c2, var = posterior_coefficients(abar_at(d, torch.tensor(12)), abar_at(d, torch.tensor(-1)))
    assert (float(c1), float(c2), float(var)) == (1.0, 0.0, 0.0)  # to the clean segment: x0 itself


def test_the_posterior_step_from_the_true_x0_keeps_the_forward_marginal():
    """x_t ~ q(x_t | x0), then x_prev ~ q(x_prev | x_t, x0): x_prev must be distributed as
    q(x_prev | x0) = N(sqrt(ab_prev) x0, 1 - ab_prev), for a large jump of a short chain."""
    d = Diffusion(50)
    g = torch.Generator().manual_seed(0)
    n = 200_000
    x0 = torch.full((n, 1), 0.7)
    t, t_prev = torch.full((n,), 49), torch.full((n,), 24)
    ab_t, ab_prev = abar_at(d, t), abar_at(d, t_prev)
    _, x_t = forward_pair(ab_t, ab_prev, x0, torch.randn(n, 1, generator=g), torch.randn(n, 1, generator=g))
    x_prev = posterior_sample(ab_t, ab_prev, x0, x_t, torch.randn(n, 1, generator=g))
    a = float(ab_prev[0])
    assert float(x_prev.mean()) == pytest.approx(0.7 * a ** 0.5, abs=0.01)
    assert float(x_prev.var()) == pytest.approx(1 - a, abs=0.01)
    assert float(x_t.var()) == pytest.approx(1 - float(ab_t[0]), abs=0.01)


def test_discriminator_shapes_gradients_and_r1():
    torch.manual_seed(0)
    D = Discriminator(frames=15, state_dim=267, hidden=64, depth=3)
    B = 5
    x_prev = torch.randn(B, 15, 267, requires_grad=True)
    x_t, cond = torch.randn(B, 15, 267), torch.randn(B, 267)
    t, t_prev = torch.tensor([49, 49, 24, 12, 37]), torch.tensor([-1, 24, -1, -1, 24])
    out = D(x_prev, x_t, cond, t, t_prev)
    assert out.shape == (B,)
    grad, = torch.autograd.grad(out.sum(), x_prev, create_graph=True)
    assert grad.shape == x_prev.shape and float(grad.detach().abs().sum()) > 0
    grad.square().sum().backward()  # R1 reaches every layer's weights (a second backward)
    linears = [m for m in D.mlp if isinstance(m, torch.nn.Linear)]
    assert all(m.weight.grad is not None and float(m.weight.grad.abs().sum()) > 0 for m in linears)
    # the two levels are told apart: the same pair at another t_prev scores otherwise
    other = D(x_prev, x_t, cond, t, torch.tensor([24, -1, 12, 12, 12]))
    assert not torch.allclose(out, other)


def test_a_latent_generator_warm_started_from_a_base_is_the_base_until_trained():
    torch.manual_seed(0)
    base = Denoiser(DenoiserConfig(**TINY))
    gen = Denoiser(DenoiserConfig(**TINY, latent=8))
    missing, unexpected = gen.load_state_dict(base.state_dict(), strict=False)
    assert not unexpected and all(k.startswith("z_mlp.") for k in missing)
    t, x_t, x0 = torch.tensor([3, 40]), torch.randn(2, 15, 267), torch.randn(2, 267)
    z = torch.randn(2, 8)
    assert torch.equal(gen(t, x_t, x0, z), base(t, x_t, x0))
    torch.nn.init.normal_(gen.z_mlp[-1].weight)  # once trained, z matters
    assert not torch.allclose(gen(t, x_t, x0, z), gen(t, x_t, x0, -z))
    with pytest.raises(ValueError, match="latent"):
        DenoiserConfig.from_dict({**TINY, "latent": -1})


def test_samplers_run_every_chain_and_only_emdm_draws_latents():
    d = Diffusion(50)
    seen = []

    def denoise(x, t, z):
        seen.append((int(t[0]), z is None))
        return torch.zeros_like(x)

    for kind, latent in (("emdm", 4), ("consistency", 0)):
        for steps in (1, 2, 4):
            seen.clear()
            out = sample(kind, d, denoise, (3, 15, 267), steps, torch.Generator().manual_seed(0), latent=latent)
            assert out.shape == (3, 15, 267)
            assert [s[0] for s in seen] == trailing_timesteps(50, steps).flip(0).tolist()
            assert all(none == (latent == 0) for _, none in seen)
    with pytest.raises(ValueError, match="kind"):
        sample("ddim", d, denoise, (1, 15, 267), 2)


def _few_step_motor(tmp_path, kind: str):
    """A tiny generator checkpoint of a few-step kind (random weights: mechanics only)."""
    base = tiny_motor(tmp_path)
    torch.manual_seed(1)
    net = Denoiser(DenoiserConfig(**TINY, latent=8 if kind == "emdm" else 0))
    net.load_state_dict(base.net.state_dict(), strict=False)
    if kind == "emdm":
        torch.nn.init.normal_(net.z_mlp[-1].weight, std=0.1)
    save_checkpoint(tmp_path / kind, net, base.norm, {"name": f"tiny-{kind}", "licence": "test only",
                                                      "sampler": {"kind": kind, "steps": 2}})
    return load_checkpoint(tmp_path / kind)


@pytest.mark.parametrize("kind", ["emdm", "consistency"])
def test_runtime_on_a_few_step_model_is_deterministic_and_a_crowd_equals_avatars_alone(tmp_path, kind):
    motor = _few_step_motor(tmp_path, kind)
    assert motor.sampler["kind"] == kind

    def run(n, seed=5):
        # (in float32: in bfloat16 a row depends on its batch by millimetres, RuntimeConfig.bfloat16_from)
        crowd = Crowd(motor, RuntimeConfig(backend="torch", bfloat16_from=0), seed)
        ids = [crowd.spawn(position=(float(k), 0.0)) for k in range(n)]
        crowd.set_goal(ids[0], (1.0, 0.0))
        return crowd, torch.stack([crowd.step_segment()[ids[0]] for _ in range(2)])

    crowd, a = run(1)
    assert crowd.cfg.steps == 2  # the checkpoint's default
    assert torch.equal(a, run(1)[1])
    # the first avatar's motion does not depend on the others (float32 batch arithmetic differs by
    # ~1e-6 per operation, through the network and post-processing of a random network's wild
    # motion; velocities are differences x 30 fps)
    from avatar_motor.body.motion_state import SLICES
    d = (a - run(3)[1]).abs()
    assert d[..., :SLICES["velocities"].start].max() < 2e-3 and d[..., SLICES["velocities"]].max() < 6e-2
    assert not torch.equal(a, run(1, seed=6)[1])
    with pytest.raises(ValueError, match="1, 2 or 4 steps"):
        Crowd(motor, RuntimeConfig(steps=8, backend="torch"))


def test_onnx_export_of_a_latent_generator_matches_torch(tmp_path):
    pytest.importorskip("onnxruntime")
    from avatar_motor.model.onnx import OnnxDenoiser, export_bytes
    motor = _few_step_motor(tmp_path, "emdm")
    ort_net = OnnxDenoiser(export_bytes(motor.net))
    g = torch.Generator().manual_seed(0)
    for B in (1, 4):
        t = torch.randint(0, 50, (B,), generator=g)
        x_t, x0, z = torch.randn(B, 15, 267, generator=g), torch.randn(B, 267, generator=g), torch.randn(B, 8, generator=g)
        with torch.inference_mode():
            ref = motor.net(t, x_t, x0, z)
        assert float((ort_net(t, x_t, x0, z) - ref).abs().max()) <= 1e-4


def test_a_checkpoint_whose_sampler_and_network_disagree_is_refused(tmp_path):
    motor = _few_step_motor(tmp_path, "emdm")
    cfg = json.loads((tmp_path / "emdm" / "config.json").read_text())
    cfg["sampler"]["kind"] = "consistency"
    (tmp_path / "emdm" / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(CheckpointError, match="latent"):
        load_checkpoint(tmp_path / "emdm")
    cfg["sampler"] = {"kind": "gan", "steps": 2}
    (tmp_path / "emdm" / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(CheckpointError, match="sampler"):
        load_checkpoint(tmp_path / "emdm")
    assert motor.net.cfg.latent == 8


def _fs_cfg(tmp_path, cache, method, out, **kw):
    from avatar_motor.data.dataset import SegmentConfig
    from avatar_motor.train.fewstep import FewStepConfig
    base = tmp_path / "tiny"
    if not base.exists():
        tiny_motor(tmp_path)
    d = dict(method=method, base=str(base), data=[str(cache)], out=str(tmp_path / out), steps=4, batch=4,
             latent=8, disc_hidden=32, disc_depth=3, checkpoint_every=2, log_every=1, ema_start=1,
             segment=SegmentConfig(split="all"))
    d.update(kw)
    return FewStepConfig(**d)


@pytest.mark.parametrize("method", ["emdm", "consistency"])
def test_few_step_training_resumes_exactly_and_exports_a_loadable_sampler(tmp_path, fixture_cache, method):  # noqa: F811
    from avatar_motor.train.fewstep import FewStepTrainer
    full = FewStepTrainer(_fs_cfg(tmp_path, fixture_cache, method, "a"), progress=False).run()
    FewStepTrainer(_fs_cfg(tmp_path, fixture_cache, method, "b"), progress=False).run(2)
    rest = FewStepTrainer(_fs_cfg(tmp_path, fixture_cache, method, "b"), progress=False)
    assert rest.step == 2
    resumed = rest.run()
    assert [m["loss"] for m in full[2:]] == pytest.approx([m["loss"] for m in resumed], rel=1e-5)
    motor = load_checkpoint(tmp_path / "b" / "checkpoint")
    assert motor.sampler["kind"] == method and motor.sampler["base"] == "tiny-test"
    assert motor.net.cfg.latent == (8 if method == "emdm" else 0)
    assert "non-commercial" in motor.config["licence"]
    crowd = Crowd(motor, RuntimeConfig(backend="torch"))
    crowd.spawn()
    assert torch.isfinite(crowd.step_segment()[0]).all()
    with pytest.raises(ValueError, match="trains"):  # another method into the same folder
        FewStepTrainer(_fs_cfg(tmp_path, fixture_cache, "consistency" if method == "emdm" else "emdm", "b"), progress=False)


def _bound_few_step_motor(tmp_path, kind: str):
    """A tiny base and a few-step model of the given kind bound to it (its base beside it, with
    the recorded fingerprint), as the shipped family is."""
    from avatar_motor.model.adaptor import base_fingerprint
    from avatar_motor.model.checkpoint import load_base
    base = tiny_motor(tmp_path)
    _few_step_motor(tmp_path, kind)
    cfg = json.loads((tmp_path / kind / "config.json").read_text())
    cfg["sampler"].update(base="tiny", base_fingerprint=base_fingerprint(base.net))
    (tmp_path / kind / "config.json").write_text(json.dumps(cfg))
    gen = load_checkpoint(tmp_path / kind)
    assert base_fingerprint(load_base(gen).net) == base_fingerprint(base.net)
    return base, gen


def test_after_an_impulse_preset_a_few_step_models_avatar_runs_on_its_teacher(tmp_path):
    """The segments after an impulse preset (RuntimeConfig.impulse_teacher of them) are sampled by
    the few-step model's DDPM base at its 8 steps, exactly as a crowd on the base makes them; the
    avatar then returns to the few-step chain, and the other avatars never leave it."""
    from avatar_motor.body.motion_state import SLICES
    from avatar_motor.runtime.sampler import ADAPTOR_STEPS
    base, gen = _bound_few_step_motor(tmp_path, "emdm")

    def run(motor, teacher=3, steps=0, segments=1):
        crowd = Crowd(motor, RuntimeConfig(backend="torch", steps=steps, impulse_teacher=teacher, bfloat16_from=0), 4)
        ids = [crowd.spawn(position=(float(k), 0.0)) for k in range(2)]
        crowd.impulse(ids[0], "back_flip")
        return crowd, [crowd.step_segment() for _ in range(segments)]

    close = lambda a, b: (a - b)[..., :SLICES["velocities"].start].abs().max() < 1e-4  # noqa: E731
    crowd, segs = run(gen, segments=4)
    on_base = run(base, steps=ADAPTOR_STEPS)[1][0]
    alone = run(gen, teacher=0)[1][0]
    assert close(segs[0][0], on_base[0]) and not close(segs[0][0], alone[0])  # the pushed one: its teacher
    assert close(segs[0][1], alone[1])  # the other: the few-step chain
    assert crowd.avatars[0].teacher_segments == 0  # 3 segments on the teacher, then back
    crowd.impulse(0, "left_kick")
    crowd.reset(0)  # a reset releases every control, the teacher's segments too
    assert crowd.avatars[0].teacher_segments == 0


def test_with_a_few_step_model_an_adaptors_avatars_run_on_its_base_as_trained(tmp_path):
    """A label adaptor trained on the base steers its avatars through the base with DDPM; the
    other avatars of the same crowd keep the few-step chain. Each avatar moves as it would in a
    crowd of its own kind."""
    from avatar_motor.model.adaptor import AdaptedDenoiser, AdaptorConfig
    from avatar_motor.runtime.sampler import ADAPTOR_STEPS
    base, gen = _bound_few_step_motor(tmp_path, "consistency")
    torch.manual_seed(3)
    ad = AdaptedDenoiser(base.net, AdaptorConfig(labels=["wave", "bow"])).eval()
    for z in ad.zero:  # a trained adaptor: its residuals are not zero
        torch.nn.init.normal_(z.weight, std=0.05)

    def first(motor, adaptor, label, n=2):
        crowd = Crowd(motor, RuntimeConfig(backend="torch", steps=ADAPTOR_STEPS if motor is base else 0), 4, adaptor)
        ids = [crowd.spawn(position=(float(k), 0.0)) for k in range(n)]
        if label:
            crowd.set_label(ids[0], "bow")
        return crowd.step_segment()

    mixed = first(gen, ad, True)
    from avatar_motor.body.motion_state import SLICES
    close = lambda a, b: (a - b)[..., :SLICES["velocities"].start].abs().max() < 1e-4  # noqa: E731
    assert close(mixed[0], first(base, ad, True)[0])  # the labelled avatar: base + adaptor, DDPM
    assert close(mixed[1], first(gen, None, False)[1])  # the other: the few-step chain
    other = AdaptedDenoiser(tiny_motor(tmp_path / "other", seed=9).net, AdaptorConfig(labels=["wave"]))
    with pytest.raises(ValueError, match="other base weights"):
        Crowd(gen, RuntimeConfig(backend="torch"), 0, other)


SHIPPED_FEW_STEP = Path(__file__).resolve().parents[1] / "models" / "primal-bandai-emdm"


@pytest.mark.skipif(not (SHIPPED_FEW_STEP / "model.safetensors").exists(), reason="the shipped few-step model is absent")
def test_the_shipped_few_step_model_is_bound_to_its_base_and_streams_one_body_deterministically():
    from avatar_motor.body.motion_state import body_mismatch
    from avatar_motor.body.skeleton import rest_offsets
    from avatar_motor.cli import DEFAULT_MODEL
    from avatar_motor.model.checkpoint import load_base
    motor = load_checkpoint(SHIPPED_FEW_STEP)
    assert DEFAULT_MODEL == SHIPPED_FEW_STEP  # what the runtime's commands run by default
    assert motor.sampler["kind"] == "emdm" and motor.sampler["steps"] == 1
    assert "non-commercial" in motor.config["licence"]
    assert load_base(motor).name == "primal-bandai"  # beside it, with the recorded fingerprint

    def run():
        crowd = Crowd(motor, RuntimeConfig(), seed=0)
        ids = [crowd.spawn(position=(2.0 * k, 0.0)) for k in range(2)]
        crowd.set_goal(ids[0], (1.0, 0.5))
        return torch.cat([torch.stack([crowd.step_segment()[i] for i in ids]) for _ in range(4)], 1)

    X = run()
    assert torch.equal(X, run())
    assert float(body_mismatch(X.double(), rest_offsets(torch.zeros(2, 6), torch.float64)[:, None]).max()) < 1e-3
    assert float(X[..., 135:201].reshape(2, -1, 22, 3)[..., 1].min()) > -0.02  # nothing under the ground
    assert float((X[0, -1, :3] - X[0, 0, :3]).norm()) > 0.5  # the steered one walks


def test_a_few_step_model_away_from_its_base_runs_without_adaptors(tmp_path):
    """The default adaptors are looked up beside the model's base; a copy without its base still
    generates, and only an adaptor asked for by name needs the base (named in the error)."""
    import shutil
    from avatar_motor.cli import FEW_STEP_MODEL, main
    if not (FEW_STEP_MODEL / "config.json").exists():
        pytest.skip("no shipped few-step model")
    shutil.copytree(FEW_STEP_MODEL, tmp_path / "alone")
    assert main(["generate", "--model", str(tmp_path / "alone"), "--seconds", "0.5", "--out", str(tmp_path / "a.bvh")]) == 0
    assert main(["generate", "--model", str(tmp_path / "alone"), "--seconds", "0.5", "--adaptor", str(tmp_path / "nope"),
                 "--out", str(tmp_path / "b.bvh")]) == 2
