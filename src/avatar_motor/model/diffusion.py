"""DDPM with a cosine (squaredcos_cap_v2) schedule and x0-prediction (PRIMAL §3.1, DESIGN §4).

Training uses T = 50 steps. Sampling can use any S <= T steps: the schedule is respaced to S of the
original timesteps (Nichol & Dhariwal 2021), keeping the model's timestep indices; `eta` = 1 gives
ancestral DDPM sampling on the respaced chain, `eta` = 0 deterministic DDIM.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch


def cosine_betas(T: int, max_beta: float = 0.999) -> torch.Tensor:
    """beta_t = min(1 - abar(t+1)/abar(t), max_beta), abar(t) = cos^2(((t/T)+0.008)/1.008 * pi/2)."""
    def abar(t):
        return math.cos((t / T + 0.008) / 1.008 * math.pi / 2) ** 2
    return torch.tensor([min(1 - abar(i + 1) / abar(i), max_beta) for i in range(T)], dtype=torch.float64)


@dataclass
class Schedule:
    """Coefficients of one (possibly respaced) chain; index k runs over its steps, timesteps[k] is
    the training timestep the model sees."""
    timesteps: torch.Tensor  # (S,) long
    betas: torch.Tensor
    alphas_cumprod: torch.Tensor
    alphas_cumprod_prev: torch.Tensor
    posterior_variance: torch.Tensor
    posterior_mean_coef1: torch.Tensor  # multiplies x0
    posterior_mean_coef2: torch.Tensor  # multiplies x_t

    @staticmethod
    def from_alphas_cumprod(abar: torch.Tensor, timesteps: torch.Tensor) -> "Schedule":
        prev = torch.cat((torch.ones(1, dtype=abar.dtype), abar[:-1]))
        betas = 1 - abar / prev
        var = betas * (1 - prev) / (1 - abar)
        return Schedule(timesteps, betas, abar, prev, var,
                        betas * prev.sqrt() / (1 - abar), (1 - prev) * (1 - betas).sqrt() / (1 - abar))


def randn(shape, generator: torch.Generator | list | None) -> torch.Tensor:
    """Gaussian noise; with a list of generators, row b of the batch comes from generator b, so a
    batch reproduces exactly what each row would get alone (crowd == individual avatars)."""
    if isinstance(generator, (list, tuple)):
        if len(generator) != shape[0]:
            raise ValueError(f"{len(generator)} generators for a batch of {shape[0]}")
        return torch.stack([torch.randn(shape[1:], generator=g) for g in generator])
    return torch.randn(shape, generator=generator)


class Diffusion:
    def __init__(self, steps: int = 50):
        self.T = steps
        betas = cosine_betas(steps)
        self.train = Schedule.from_alphas_cumprod(torch.cumprod(1 - betas, 0), torch.arange(steps))

    def respaced(self, steps: int) -> Schedule:
        if not 1 <= steps <= self.T:
            raise ValueError(f"sampling steps must be between 1 and {self.T}, got {steps}")
        if steps == self.T:
            return self.train
        # every chain ends at the fully noised timestep, where sampling starts from pure noise
        # (linspace alone gives a single step timestep 0)
        ts = torch.linspace(0, self.T - 1, steps).round().long().unique() if steps > 1 else torch.tensor([self.T - 1])
        return Schedule.from_alphas_cumprod(self.train.alphas_cumprod[ts], ts)

    def q_sample(self, x0: torch.Tensor, t: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        ab = self.train.alphas_cumprod.to(x0.dtype)[t].view(-1, *([1] * (x0.dim() - 1)))
        return ab.sqrt() * x0 + (1 - ab).sqrt() * noise

    @staticmethod
    def posterior(s: Schedule, k: int, x0_hat: torch.Tensor, x_t: torch.Tensor) -> tuple[torch.Tensor, float]:
        """Mean and variance of q(x_{k-1} | x_k, x0_hat) on chain s."""
        mean = s.posterior_mean_coef1[k].item() * x0_hat + s.posterior_mean_coef2[k].item() * x_t
        return mean, s.posterior_variance[k].item()

    def sample(self, denoise, shape, steps: int = 50, generator: torch.Generator | list | None = None,
               guide=None, eta: float = 1.0, noise: torch.Tensor | None = None) -> torch.Tensor:
        """Reverse diffusion. denoise(x_t, t_long) -> x0_hat.

        guide(x0_hat) -> guided x0 estimate: the guidance losses' gradient steps are applied to the
        x0 estimate before the posterior is formed (the posterior mean moves by coef1 times the
        step). The last step is left to the network, so the output is always its own,
        self-consistent estimate of the guided trajectory."""
        s = self.respaced(steps)
        x = randn(shape, generator) if noise is None else noise
        for k in range(len(s.timesteps) - 1, -1, -1):
            t = torch.full((shape[0],), int(s.timesteps[k]), dtype=torch.long)
            x0 = denoise(x, t)
            if k == 0:
                x = x0
                break
            if guide is not None:
                x0 = guide(x0)
            if eta >= 1.0:
                mean, var = self.posterior(s, k, x0, x)
                x = mean + math.sqrt(var) * randn(shape, generator)
            else:  # DDIM
                ab, ab_prev = s.alphas_cumprod[k].item(), s.alphas_cumprod_prev[k].item()
                eps = (x - math.sqrt(ab) * x0) / math.sqrt(1 - ab)
                sigma = eta * math.sqrt((1 - ab_prev) / (1 - ab) * (1 - ab / ab_prev))
                x = math.sqrt(ab_prev) * x0 + math.sqrt(max(1 - ab_prev - sigma**2, 0.0)) * eps
                if sigma > 0:
                    x = x + sigma * randn(shape, generator)
        return x
