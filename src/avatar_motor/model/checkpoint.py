"""Checkpoints as folders: model.safetensors (no pickle), config.json, card.md (DESIGN §4).

config.json holds the architecture, the state layout, the normalisation statistics, the diffusion
schedule, the training data and the licence. Loading validates all of it and names any mismatch.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

from ..data.dataset import Normalizer
from ..body.motion_state import SLICES, STATE_DIM
from ..io.atomic import replace_folder
from .denoiser import Denoiser, DenoiserConfig
from .diffusion import Diffusion
from .fewstep import sampler_of

FORMAT = "avatar-motor-checkpoint/1"
STATE_LAYOUT = {k: [v.start, v.stop] for k, v in SLICES.items()}


class CheckpointError(ValueError):
    """A checkpoint folder is missing, corrupt or does not match this code."""


@dataclass
class Motor:
    """A loaded base model: network, normalisation, diffusion schedule and its config."""
    net: Denoiser
    norm: Normalizer
    diffusion: Diffusion
    config: dict
    path: Path | None = None

    @property
    def sampler(self) -> dict:
        """How this network samples: {"kind": "ddpm" | "emdm" | "consistency", "steps": default, ...}."""
        return sampler_of(self.config)

    @property
    def name(self) -> str:
        return self.config.get("name", self.path.name if self.path else "model")


def checkpoint_complete(folder: Path) -> bool:
    """A checkpoint folder whose files were all written (card.md is written last)."""
    return all((Path(folder) / f).exists() for f in ("model.safetensors", "config.json", "card.md"))


def save_checkpoint(folder: str | Path, net: Denoiser, norm: Normalizer, extra: dict | None = None,
                    card: str | None = None, diffusion_steps: int = 50, half: bool = False) -> Path:
    """Write so that a kill at any instant leaves the old checkpoint or the new one (io/atomic.py).
    half=True stores the weights as float16 (half the size; loading casts back to float32)."""
    cfg = {
        "format": FORMAT,
        "denoiser": net.cfg.to_dict(),
        "state_layout": STATE_LAYOUT,
        "state_dim": STATE_DIM,
        "diffusion": {"train_steps": diffusion_steps, "schedule": "squaredcos_cap_v2", "prediction": "x0"},
        "normalizer": norm.to_dict(),
        **(extra or {}),
    }
    dtype = torch.float16 if half else torch.float32

    def fill(tmp: Path) -> None:
        save_file({k: v.detach().to(dtype).contiguous().cpu() for k, v in net.state_dict().items()}, str(tmp / "model.safetensors"))
        (tmp / "config.json").write_text(json.dumps(cfg, indent=1))
        (tmp / "card.md").write_text(card or f"# {Path(folder).name}\n\nNo card was written for this checkpoint.\n")

    return replace_folder(folder, fill, checkpoint_complete)


def ship_checkpoint(src: str | Path, dst: str | Path, card: str, extra: dict | None = None) -> Path:
    """Copy a trained checkpoint into a shippable one: float16 weights, a card, extra config."""
    m = load_checkpoint(src)
    cfg = {k: v for k, v in m.config.items() if k not in ("format", "denoiser", "state_layout", "state_dim", "diffusion", "normalizer")}
    cfg.update(extra or {})
    return save_checkpoint(dst, m.net, m.norm, cfg, card, m.diffusion.T, half=True)


def load_checkpoint(folder: str | Path) -> Motor:
    folder = Path(folder)
    if not folder.is_dir():
        raise CheckpointError(f"{folder}: no such checkpoint folder. Pass a folder with model.safetensors and config.json "
                              "(the shipped model is models/primal-bandai)")
    cfg_path, w_path = folder / "config.json", folder / "model.safetensors"
    for p in (cfg_path, w_path):
        if not p.exists():
            raise CheckpointError(f"{folder}: {p.name} is missing; this is not a complete checkpoint")
    try:
        cfg = json.loads(cfg_path.read_text())
    except json.JSONDecodeError as e:
        raise CheckpointError(f"{cfg_path}: not valid JSON ({e}); the checkpoint is corrupt") from None
    if not isinstance(cfg, dict):
        raise CheckpointError(f"{cfg_path}: must hold a JSON object, got {type(cfg).__name__}; the checkpoint is corrupt")
    if cfg.get("format") != FORMAT:
        raise CheckpointError(f"{cfg_path}: format {cfg.get('format')!r} is not {FORMAT!r}; this is not an avatar-motor checkpoint")
    if cfg.get("state_layout") != STATE_LAYOUT or cfg.get("state_dim") != STATE_DIM:
        raise CheckpointError(f"{cfg_path}: motion-state layout {cfg.get('state_layout')} differs from this code's {STATE_LAYOUT}; "
                              "retrain or use a matching version")
    diff = cfg.get("diffusion")
    steps = diff.get("train_steps") if isinstance(diff, dict) else None
    if isinstance(steps, bool) or not isinstance(steps, int) or not 1 <= steps <= 10000:
        raise CheckpointError(f"{cfg_path}: diffusion.train_steps must be an integer in [1, 10000], got {steps!r}")
    try:
        dcfg = DenoiserConfig.from_dict(cfg.get("denoiser"))  # every field checked before allocation
        norm = Normalizer.from_dict(cfg["normalizer"])
        kind = sampler_of(cfg)["kind"]
        if (dcfg.latent > 0) != (kind == "emdm"):
            raise ValueError(f"a {kind} sampler with a latent of {dcfg.latent} does not exist: EMDM generators, and "
                             "only they, have a latent")
    except (KeyError, ValueError, TypeError) as e:
        raise CheckpointError(f"{cfg_path}: invalid config ({e})") from None
    with torch.random.fork_rng():  # its random init is overwritten: loading leaves the caller's random stream alone
        net = Denoiser(dcfg)
    try:
        weights = load_file(str(w_path))
    except Exception as e:  # safetensors raises several error types on garbage
        raise CheckpointError(f"{w_path}: cannot read the weights ({e}); the file is corrupt or truncated") from None
    own = net.state_dict()
    missing = sorted(set(own) - set(weights))
    extra = sorted(set(weights) - set(own))
    bad = sorted(k for k in set(own) & set(weights) if own[k].shape != weights[k].shape)
    if missing or extra or bad:
        detail = "; ".join(x for x in (
            f"missing {missing[:5]}" if missing else "", f"unexpected {extra[:5]}" if extra else "",
            "shape mismatch " + ", ".join(f"{k} {tuple(weights[k].shape)} vs {tuple(own[k].shape)}" for k in bad[:5]) if bad else "") if x)
        raise CheckpointError(f"{w_path}: weights do not match config.json ({detail})")
    for k, v in weights.items():
        if not torch.isfinite(v).all():
            raise CheckpointError(f"{w_path}: tensor {k} contains NaN or infinite values")
    net.load_state_dict({k: v.float() for k, v in weights.items()})
    net.eval()
    return Motor(net, norm, Diffusion(steps), cfg, folder)


def load_base(motor: Motor) -> Motor:
    """The DDPM base a few-step model was warm-started from: the checkpoint folder beside it named
    in its sampler entry, checked against the recorded fingerprint. A base is its own base."""
    s = motor.sampler
    if s["kind"] == "ddpm":
        return motor
    from .adaptor import base_fingerprint
    folder = (motor.path.parent if motor.path else Path(".")) / str(s.get("base"))
    if not (folder / "config.json").exists():
        raise CheckpointError(f"{motor.path}: its base {s.get('base')!r} is not beside it ({folder}); adaptors run on "
                              "that base: put it there or pass the base as --model")
    base = load_checkpoint(folder)
    if base_fingerprint(base.net) != s.get("base_fingerprint"):
        raise CheckpointError(f"{folder}: not the weights {motor.name} was trained from (the base was retrained "
                              "since); rebuild the few-step model on this base")
    return base
