"""Few-step samplers beside the DDPM one (DESIGN §4): EMDM's denoising-diffusion GAN (EMDM §3,
Algorithms 1-2) and consistency distillation (as MotionLCM does), both on chains of 1, 2 or 4
large steps of the base's 50-step cosine schedule.

Chains use trailing spacing (the last step starts from the fully noised timestep T-1, e.g.
[11, 24, 37, 49] for 4 steps): a chain must begin where the noise is pure, which linspace spacing
does not do for one step. Index -1 of a chain stands for the clean segment.

What a few-step model is, is written in its checkpoint: `config.json["sampler"]` = {"kind":
"emdm" | "consistency", "steps": the default number of steps, "base": the base it was
warm-started from, "base_fingerprint": its weights}. A plain base has no such entry and samples
with DDPM.
"""
from __future__ import annotations

import torch
from torch import nn

from .denoiser import timestep_embedding
from .diffusion import Diffusion, randn

KINDS = ("ddpm", "emdm", "consistency")
FEW_STEPS = (1, 2, 4)


def trailing_timesteps(T: int, steps: int) -> torch.Tensor:
    """The training timesteps a chain of `steps` visits, ascending, ending at T-1."""
    if not 1 <= steps <= T:
        raise ValueError(f"a chain has between 1 and {T} steps, got {steps}")
    return (torch.arange(1, steps + 1, dtype=torch.float64) * T / steps).round().long() - 1


def abar_at(diffusion: Diffusion, t: torch.Tensor) -> torch.Tensor:
    """alpha-bar at training timesteps t (long, any shape); t = -1 is the clean segment (1)."""
    ab = torch.cat((torch.ones(1, dtype=torch.float64), diffusion.train.alphas_cumprod))
    return ab[t + 1]


def posterior_coefficients(ab_t: torch.Tensor, ab_prev: torch.Tensor):
    """q(x_prev | x_t, x0) = N(c1 x0 + c2 x_t, var) between two noise levels of the forward
    process (alpha-bars ab_t < ab_prev; ab_prev = 1 is the clean segment, where c1 = 1, c2 = var = 0).
    Tensors of any matching shape; returns (c1, c2, var)."""
    alpha = ab_t / ab_prev  # the one-step alpha of the jump
    beta = 1 - alpha
    c1 = beta * ab_prev.sqrt() / (1 - ab_t)
    c2 = (1 - ab_prev) * alpha.sqrt() / (1 - ab_t)
    var = beta * (1 - ab_prev) / (1 - ab_t)
    return c1, c2, var


def _rows(v: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    return v.to(like.dtype).view(-1, *([1] * (like.dim() - 1)))


def posterior_sample(ab_t, ab_prev, x0_hat: torch.Tensor, x_t: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
    """EMDM Algorithm 2 per row: x_prev ~ q(x_prev | x_t, x0 = x0_hat), given its noise. ab_t,
    ab_prev: (B,) alpha-bars of the two levels."""
    c1, c2, var = posterior_coefficients(ab_t, ab_prev)
    return _rows(c1, x_t) * x0_hat + _rows(c2, x_t) * x_t + _rows(var.sqrt(), x_t) * noise


def forward_pair(ab_t, ab_prev, x0: torch.Tensor, noise_prev: torch.Tensor, noise_t: torch.Tensor):
    """A real pair of EMDM Eq. 5: x_prev ~ q(x_prev | x0), then x_t ~ q(x_t | x_prev)."""
    x_prev = _rows(ab_prev.sqrt(), x0) * x0 + _rows((1 - ab_prev).sqrt(), x0) * noise_prev
    a = ab_t / ab_prev
    x_t = _rows(a.sqrt(), x0) * x_prev + _rows((1 - a).sqrt(), x0) * noise_t
    return x_prev, x_t


class Discriminator(nn.Module):
    """D(x_prev, x_t, c, t) of EMDM §3.1 (Eq. 4-6): an MLP over the flattened pair, the condition
    (our initial state) and embeddings of both noise levels, as EMDM's default is. An MLP because a
    segment is short (15 frames: the pair is 8,010 numbers), so one layer sees every frame jointly,
    it costs a small fraction of the generator per step, and R1's gradient penalty (a second
    backward pass) through it is cheap. Both levels are embedded because one generator serves
    chains of 1, 2 and 4 steps: from timestep 49 the next level is 37, 24 or the clean segment."""

    def __init__(self, frames: int, state_dim: int, hidden: int = 512, depth: int = 5, embed: int = 128):
        super().__init__()
        self.embed = embed
        d_in = 2 * frames * state_dim + state_dim + 2 * embed
        layers: list[nn.Module] = []
        for i in range(depth - 1):
            layers += [nn.Linear(d_in if i == 0 else hidden, hidden), nn.LeakyReLU(0.2)]
        layers.append(nn.Linear(hidden, 1))
        self.mlp = nn.Sequential(*layers)

    def forward(self, x_prev, x_t, cond, t, t_prev) -> torch.Tensor:
        """x_prev, x_t (B, frames, D) normalised; cond (B, D) the normalised initial state; t, t_prev
        (B,) long training timesteps (t_prev = -1: clean). Returns logits (B,): real > 0."""
        e = torch.cat((timestep_embedding(t, self.embed), timestep_embedding(t_prev + 1, self.embed)), -1)
        return self.mlp(torch.cat((x_prev.flatten(1), x_t.flatten(1), cond, e), -1))[:, 0]


def sample(kind: str, diffusion: Diffusion, denoise, shape, steps: int, generator=None, guide=None,
           latent: int = 0) -> torch.Tensor:
    """A few-step chain. denoise(x_t, t_long, z) -> x0_hat (z is None unless `latent`).

    emdm (Algorithm 1): at each step a fresh z, x0_hat = G(x_t, z), x_prev drawn from the
    posterior q(x_prev | x_t, x0_hat). consistency (multistep consistency sampling): x0_hat =
    f(x_t), then forward-noised to the next level with fresh noise. guide(x0_hat) as in
    Diffusion.sample: applied before every step but the last, which is the network's own."""
    if kind not in ("emdm", "consistency"):
        raise ValueError(f"few-step sampler kind must be 'emdm' or 'consistency', got {kind!r}")
    ts = trailing_timesteps(diffusion.T, steps)
    B = shape[0]
    x = randn(shape, generator)
    for k in range(steps - 1, -1, -1):
        t = torch.full((B,), int(ts[k]), dtype=torch.long)
        z = randn((B, latent), generator) if latent else None
        x0 = denoise(x, t, z)
        if k == 0:
            return x0
        if guide is not None:
            x0 = guide(x0)
        ab_prev = abar_at(diffusion, ts[k - 1:k]).expand(B)
        noise = randn(shape, generator)
        if kind == "emdm":
            x = posterior_sample(abar_at(diffusion, t), ab_prev, x0, x, noise)
        else:
            x = _rows(ab_prev.sqrt(), x0) * x0 + _rows((1 - ab_prev).sqrt(), x0) * noise
    return x


def sampler_of(config: dict) -> dict:
    """The sampler entry of a checkpoint config, checked; a plain base samples with DDPM."""
    s = config.get("sampler")
    if s is None:
        return {"kind": "ddpm", "steps": 8}
    if not isinstance(s, dict) or s.get("kind") not in KINDS:
        raise ValueError(f"checkpoint 'sampler' must be an object with kind in {KINDS}, got {s!r}")
    steps = s.get("steps")
    if isinstance(steps, bool) or not isinstance(steps, int) or not 1 <= steps <= 50:
        raise ValueError(f"checkpoint sampler 'steps' must be an integer in [1, 50], got {steps!r}")
    return s


def check_steps(kind: str, steps: int) -> None:
    if kind != "ddpm" and steps not in FEW_STEPS:
        raise ValueError(f"the {kind} sampler runs 1, 2 or 4 steps, not {steps}: pass --steps 1, 2 or 4 "
                         "(or 0, the model's default)")

