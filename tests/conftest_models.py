"""Models for tests: the shipped model when present, else a tiny random one (mechanics only)."""
from pathlib import Path

import torch

from avatar_motor.data.dataset import Normalizer
from avatar_motor.body.motion_state import STATE_DIM
from avatar_motor.model.checkpoint import load_checkpoint, save_checkpoint
from avatar_motor.model.denoiser import Denoiser, DenoiserConfig

SHIPPED = Path(__file__).resolve().parents[1] / "models" / "primal-bandai"


def tiny_motor(tmp_path: Path, seed: int = 0):
    torch.manual_seed(seed)
    net = Denoiser(DenoiserConfig(width=32, depth=2, heads=4, ff=64, dropout=0.0))
    # statistics that keep decoded samples near a plausible body: real-unit scales
    norm = Normalizer(torch.zeros(STATE_DIM), torch.full((STATE_DIM,), 0.05))
    save_checkpoint(tmp_path / "tiny", net, norm, {"name": "tiny-test", "licence": "test only"})
    return load_checkpoint(tmp_path / "tiny")


def shipped_or_tiny(tmp_path: Path):
    return load_checkpoint(SHIPPED) if (SHIPPED / "model.safetensors").exists() else tiny_motor(tmp_path)


SHIPPED_PERSONA = SHIPPED.parent / "primal-bandai-persona"


def persona_or_tiny(tmp_path: Path):
    """The shipped persona model, else a tiny random one with persona conditions (mechanics only)."""
    if (SHIPPED_PERSONA / "model.safetensors").exists():
        return load_checkpoint(SHIPPED_PERSONA)
    torch.manual_seed(0)
    net = Denoiser(DenoiserConfig(width=32, depth=2, heads=4, ff=64, dropout=0.0, persona=True))
    norm = Normalizer(torch.zeros(STATE_DIM), torch.full((STATE_DIM,), 0.05))
    save_checkpoint(tmp_path / "ptiny", net, norm, {"name": "tiny-persona-test", "licence": "test only"})
    return load_checkpoint(tmp_path / "ptiny")
