"""The denoiser G(t, X_t, x_0) -> X0_hat (PRIMAL §3.3, Fig. 2, supplementary §8.1).

InContext: the time embedding and the initial-state embedding are added into one prefix token,
concatenated with the frame tokens; pre-norm transformer blocks with SiLU feed-forward; learned
positional encoding. AdaLN: DiT blocks whose LayerNorm scale/shift/gate come from the summed
condition (adaLN-zero). Both keep the blocks in a ModuleList so adaptors can wrap each block.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

import torch
import torch.nn.functional as F
from torch import nn

from ..body.motion_state import STATE_DIM


@dataclass
class DenoiserConfig:
    arch: str = "incontext"  # or "adaln"
    state_dim: int = STATE_DIM
    frames: int = 15
    width: int = 256
    depth: int = 6
    heads: int = 8
    ff: int = 1024
    dropout: float = 0.1
    latent: int = 0  # size of EMDM's latent z (0: a plain denoiser); z enters the condition token
    persona: bool = False  # text, shape and trajectory conditions (model/persona.py)
    # in-diffusion blending (MotionPersona Eq. 4): the first `blend` noisy frames the network sees are
    # pulled towards the initial state, linearly from full to none (0: off)
    blend: int = 0

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d) -> "DenoiserConfig":
        """Field by field, before anything is allocated: a config that is not an object, a field of
        the wrong type or out of range, or a network too large for this project is refused with a
        ValueError naming the field."""
        if not isinstance(d, dict):
            raise ValueError(f"the denoiser config must be an object of fields, got {type(d).__name__}")
        unknown = sorted(set(d) - {f.name for f in fields(cls)})
        if unknown:
            raise ValueError(f"unknown denoiser fields {unknown}")
        cfg = cls(**d)
        ints = {"state_dim": (STATE_DIM, STATE_DIM), "frames": (2, 240), "width": (8, 4096), "depth": (1, 64),
                "heads": (1, 64), "ff": (8, 16384), "latent": (0, 1024), "blend": (0, 240)}
        for name, (lo, hi) in ints.items():
            v = getattr(cfg, name)
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                raise ValueError(f"denoiser field {name!r} must be an integer in [{lo}, {hi}], got {v!r}")
        if cfg.arch not in ("incontext", "adaln"):
            raise ValueError(f"denoiser field 'arch' must be 'incontext' or 'adaln', got {cfg.arch!r}")
        if isinstance(cfg.dropout, bool) or not isinstance(cfg.dropout, (int, float)) or not 0 <= cfg.dropout < 1:
            raise ValueError(f"denoiser field 'dropout' must be a number in [0, 1), got {cfg.dropout!r}")
        if not isinstance(cfg.persona, bool):
            raise ValueError(f"denoiser field 'persona' must be true or false, got {cfg.persona!r}")
        if cfg.blend > cfg.frames:
            raise ValueError(f"denoiser 'blend' {cfg.blend} is more than its {cfg.frames} frames")
        if cfg.width % cfg.heads:
            raise ValueError(f"denoiser 'width' {cfg.width} must be a multiple of 'heads' {cfg.heads}")
        params = cfg.depth * (4 * cfg.width ** 2 + 2 * cfg.width * cfg.ff)
        if params > 2e8:
            raise ValueError(f"a denoiser of about {params / 1e6:.0f} M parameters is beyond what this project runs")
        return cfg


def timestep_embedding(t: torch.Tensor, dim: int, max_period: float = 10000.0) -> torch.Tensor:
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, dtype=torch.float32) / half)
    args = t.float()[:, None] * freqs[None]
    return torch.cat((torch.cos(args), torch.sin(args)), -1)


class Attention(nn.Module):
    def __init__(self, width: int, heads: int, dropout: float):
        super().__init__()
        self.heads = heads
        self.qkv = nn.Linear(width, 3 * width)
        self.out = nn.Linear(width, width)
        self.dropout = dropout

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        B, N, C = x.shape
        q, k, v = self.qkv(x).view(B, N, 3, self.heads, C // self.heads).permute(2, 0, 3, 1, 4)
        y = F.scaled_dot_product_attention(q, k, v, dropout_p=self.dropout if self.training else 0.0)
        return self.out(y.transpose(1, 2).reshape(B, N, C))


class FeedForward(nn.Sequential):
    def __init__(self, width: int, ff: int, dropout: float):
        super().__init__(nn.Linear(width, ff), nn.SiLU(), nn.Dropout(dropout), nn.Linear(ff, width))


class Block(nn.Module):
    """Pre-norm transformer block; `cond` is used only by the AdaLN variant."""

    def __init__(self, cfg: DenoiserConfig):
        super().__init__()
        w = cfg.width
        self.adaln = cfg.arch == "adaln"
        self.norm1 = nn.LayerNorm(w, elementwise_affine=not self.adaln)
        self.attn = Attention(w, cfg.heads, cfg.dropout)
        self.norm2 = nn.LayerNorm(w, elementwise_affine=not self.adaln)
        self.ff = FeedForward(w, cfg.ff, cfg.dropout)
        self.drop = nn.Dropout(cfg.dropout)
        if self.adaln:
            self.modulation = nn.Sequential(nn.SiLU(), nn.Linear(w, 6 * w))
            nn.init.zeros_(self.modulation[1].weight)
            nn.init.zeros_(self.modulation[1].bias)

    def forward(self, x: torch.Tensor, cond: torch.Tensor | None = None) -> torch.Tensor:
        if not self.adaln:
            x = x + self.drop(self.attn(self.norm1(x)))
            return x + self.drop(self.ff(self.norm2(x)))
        sh1, sc1, g1, sh2, sc2, g2 = self.modulation(cond)[:, None].chunk(6, -1)
        x = x + g1 * self.drop(self.attn(self.norm1(x) * (1 + sc1) + sh1))
        return x + g2 * self.drop(self.ff(self.norm2(x) * (1 + sc2) + sh2))


class Denoiser(nn.Module):
    def __init__(self, cfg: DenoiserConfig):
        super().__init__()
        if cfg.arch not in ("incontext", "adaln"):
            raise ValueError(f"unknown denoiser arch {cfg.arch!r}; use 'incontext' or 'adaln'")
        self.cfg = cfg
        w = cfg.width
        self.time_mlp = nn.Sequential(nn.Linear(w, w), nn.SiLU(), nn.Linear(w, w))
        self.x0_embed = nn.Linear(cfg.state_dim, w)
        self.in_proj = nn.Linear(cfg.state_dim, w)
        n_tok = cfg.frames + (1 if cfg.arch == "incontext" else 0)
        self.pos = nn.Parameter(torch.randn(1, n_tok, w) * 0.02)
        self.blocks = nn.ModuleList(Block(cfg) for _ in range(cfg.depth))
        self.norm_out = nn.LayerNorm(w)
        self.out = nn.Linear(w, cfg.state_dim)
        if cfg.latent:
            # EMDM's latent through a small MLP, added into the condition token (ours sums the
            # time and the initial state there already). Zero-initialised output: a generator
            # warm-started from a base is that base exactly at its first step.
            self.z_mlp = nn.Sequential(nn.Linear(cfg.latent, w), nn.SiLU(), nn.Linear(w, w), nn.SiLU(),
                                       nn.Linear(w, w))
            nn.init.zeros_(self.z_mlp[-1].weight)
            nn.init.zeros_(self.z_mlp[-1].bias)
        if cfg.persona:
            from .persona import PersonaEmbedding
            self.persona = PersonaEmbedding(w)

    def condition(self, t: torch.Tensor, x0: torch.Tensor, z: torch.Tensor | None = None) -> torch.Tensor:
        """Summed time + initial-state (+ latent) embedding (B, width). A latent network given no z
        uses z = 0, the mode of p(z)."""
        c = self.time_mlp(timestep_embedding(t, self.cfg.width).to(x0.dtype)) + self.x0_embed(x0)
        if self.cfg.latent:
            c = c + self.z_mlp(z if z is not None else x0.new_zeros(len(x0), self.cfg.latent))
        return c

    def blended(self, x_t: torch.Tensor, x0: torch.Tensor) -> torch.Tensor:
        """MotionPersona's in-diffusion blending (Eq. 4) of the noisy frames with the initial state,
        inside the network so that training, every sampler and the ONNX export see the same."""
        M = self.cfg.blend
        if not M:
            return x_t
        w = torch.zeros(x_t.shape[1], dtype=x_t.dtype)
        w[:M] = torch.linspace(1.0, 0.0, M + 1, dtype=x_t.dtype)[:M]
        return x_t + w[:, None] * (x0[:, None] - x_t)

    def tokens(self, x_t: torch.Tensor, cond: torch.Tensor, frames: torch.Tensor | None = None) -> torch.Tensor:
        """The token sequence; `frames` (B, frames, width) is added to the frame tokens."""
        h = self.in_proj(x_t)
        if frames is not None:
            h = h + frames
        if self.cfg.arch == "incontext":
            h = torch.cat((cond[:, None], h), 1)
        return h + self.pos

    def head(self, h: torch.Tensor) -> torch.Tensor:
        if self.cfg.arch == "incontext":
            h = h[:, 1:]
        return self.out(self.norm_out(h))

    def forward(self, t: torch.Tensor, x_t: torch.Tensor, x0: torch.Tensor, z: torch.Tensor | None = None,
                persona=None) -> torch.Tensor:
        """t (B,) long, x_t (B, frames, D) noisy normalized segment, x0 (B, D) normalized initial
        state, z (B, latent) EMDM's latent (latent networks only), persona a PersonaCond (persona
        networks; None: no condition)."""
        cond = self.condition(t, x0, z)
        frames = None
        if persona is not None and self.cfg.persona:
            c, frames = self.persona(persona, cond.dtype)
            cond = cond + c
        h = self.tokens(self.blended(x_t, x0), cond, frames)
        for blk in self.blocks:
            h = blk(h, cond)
        return self.head(h)
