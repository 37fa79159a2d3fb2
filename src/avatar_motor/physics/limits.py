"""Range of motion from data (DROP §4 E_RoM, §7): each joint's local rotation must stay near the
rotations real people take. DROP projects through VPoser's latent; we have no such model, so the
set is the data's own: per joint, K anchor rotations spread over what the training motion holds
(farthest-point sampling), and a radius that keeps 99 % of held-out real rotations inside. A
rotation farther than the radius from every anchor is turned toward the nearest anchor until it is
on the boundary: swing and twist limits together, shaped like the data, not like a cone."""
from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

from ..body import rotations as rot

ANCHORS = 256  # per joint
COVER = 0.99  # share of held-out real rotations the set contains


@dataclass
class RangeOfMotion:
    anchors: torch.Tensor  # (21, K, 4) unit quaternions w, x, y, z (w >= 0)
    radius: torch.Tensor  # (21,) rad


def _angles(q: torch.Tensor, anchors: torch.Tensor) -> torch.Tensor:
    """Angles (..., 21, K) between rotations q (..., 21, 4) and each joint's anchors (21, K, 4)."""
    dot = (q[..., None, :] * anchors).sum(-1).abs().clamp(max=1.0)
    return 2 * torch.acos(dot)


def fit(local_rot: torch.Tensor, held_out: torch.Tensor, anchors: int = ANCHORS, cover: float = COVER,
        generator: torch.Generator | None = None, pool: int = 20000) -> RangeOfMotion:
    """Limits from real local rotations (N, 21, 3, 3) (training frames) checked on held_out
    (M, 21, 3, 3): anchors by farthest-point sampling among at most `pool` training frames, the
    radius the `cover` quantile of the held-out frames' distances to their nearest anchor."""
    q = rot.matrix_to_quat(local_rot.to(torch.float64))
    if len(q) > pool:
        q = q[torch.randperm(len(q), generator=generator)[:pool]]
    J = q.shape[1]
    chosen = torch.zeros(J, anchors, 4, dtype=torch.float64)
    chosen[:, 0] = q[0]
    nearest = _angles(q, chosen[:, :1]).squeeze(-1)  # (N, 21) distance to the chosen set
    for k in range(1, anchors):
        far = nearest.argmax(0)  # per joint, the rotation farthest from the set so far
        chosen[:, k] = q[far, torch.arange(J)]
        nearest = torch.minimum(nearest, _angles(q, chosen[:, k:k + 1]).squeeze(-1))
    d = _angles(rot.matrix_to_quat(held_out.to(torch.float64)), chosen).amin(-1)  # (M, 21)
    return RangeOfMotion(chosen, torch.quantile(d, cover, dim=0))


def excess(local_rot: torch.Tensor, rom: RangeOfMotion) -> torch.Tensor:
    """(..., 21) rad: how far each joint's rotation of local_rot (..., 21, 3, 3) lies beyond its
    radius from the nearest anchor (<= 0: inside the range)."""
    return _angles(rot.matrix_to_quat(local_rot.to(torch.float64)), rom.anchors.to(torch.float64)).amin(-1) - rom.radius


def project(local_rot: torch.Tensor, rom: RangeOfMotion) -> torch.Tensor:
    """Local rotations (..., 21, 3, 3) moved into the range: one farther than its joint's radius
    from every anchor is slerped toward the nearest anchor onto the radius; others unchanged."""
    q = rot.matrix_to_quat(local_rot.to(torch.float64))
    ang = _angles(q, rom.anchors.to(q.dtype))
    d, k = ang.min(-1)  # (..., 21)
    a = rom.anchors.to(q.dtype)[torch.arange(q.shape[-2]), k]  # (..., 21, 4) nearest anchors
    a = torch.where((a * q).sum(-1, keepdim=True) < 0, -a, a)  # same hemisphere as q
    radius = rom.radius.to(q.dtype)
    out = rot.quat_slerp(a, q, (radius / d.clamp_min(1e-12)).clamp(max=1.0))  # from the anchor, radius along
    return torch.where((d > radius)[..., None, None], rot.quat_to_matrix(out), local_rot.to(torch.float64))


def save(rom: RangeOfMotion, path: str | Path) -> None:
    """float16, like every shipped artifact (an anchor moves by under 0.1 degree)."""
    save_file({"anchors": rom.anchors.to(torch.float16).contiguous(), "radius": rom.radius.to(torch.float16).contiguous()},
              str(path))


def fingerprint(rom: RangeOfMotion) -> str:
    """16 hex digits over the float16 values: the shipped file's own."""
    h = hashlib.sha256()
    for t in (rom.anchors, rom.radius):
        h.update(t.to(torch.float16).contiguous().numpy().tobytes())
    return h.hexdigest()[:16]


FILE = "range_of_motion.safetensors"


@dataclass
class LimitsConfig:
    """The recipe of the shipped range of motion (configs/range-of-motion.json)."""
    data: list[str] = field(default_factory=lambda: ["dataset-1", "dataset-2", "deepmimic"])
    anchors: int = ANCHORS
    cover: float = COVER
    pool: int = 20000  # training frames the anchors are chosen among
    held_out: int = 20000  # held-out frames the radius is set on
    seed: int = 0
    out: str = "models/range-of-motion"


def fit_job(cfg: LimitsConfig, caches) -> tuple[RangeOfMotion, dict]:
    """Fit on the caches' training clips, set the radius on and measure on their held-out clips:
    returns the range and its figures (what the card states)."""
    from ..eval.realism import training_poses

    g = torch.Generator().manual_seed(cfg.seed)
    train = training_poses(caches, cfg.pool, g)
    held = training_poses(caches, cfg.held_out, g, held_out=True)
    rom = fit(train, held[: len(held) // 2], cfg.anchors, cfg.cover, g, cfg.pool)
    check = held[len(held) // 2:]  # frames the radius was not set on
    inside = excess(check, rom) <= 0  # (M, 21)
    figures = {"joints_inside": float(inside.float().mean()), "frames_all_inside": float(inside.all(-1).float().mean()),
               "radius_deg_median": float(torch.rad2deg(rom.radius).median()),
               "radius_deg_max": float(torch.rad2deg(rom.radius).max())}
    return rom, figures


def ship(rom: RangeOfMotion, cfg: LimitsConfig, figures: dict, card: str) -> Path:
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / (FILE + ".tmp")
    save(rom, tmp)
    shipped = load(tmp)  # figures are of the float16 values that ship
    tmp.replace(out / FILE)
    info = {"kind": "range_of_motion", "recipe": asdict(cfg), "fingerprint": fingerprint(shipped), "figures": figures}
    (out / "config.json").write_text(json.dumps(info, indent=1) + "\n")
    (out / "card.md").write_text(card)
    return out / FILE


def default_range(models: str | Path) -> RangeOfMotion | None:
    """The shipped range of motion in the models folder, or None (then physics mode runs without
    joint limits) when it has not been built."""
    path = Path(models) / "range-of-motion" / FILE
    return load(path) if path.exists() else None


def load(path: str | Path) -> RangeOfMotion:
    try:
        t = load_file(str(path))
        rom = RangeOfMotion(t["anchors"].to(torch.float64), t["radius"].to(torch.float64))
    except Exception as e:  # noqa: BLE001 - any unreadable file gets the same clear message
        raise ValueError(f"{path}: not a readable range-of-motion file ({e}); rebuild it from motion "
                         "data: avatar-motor limits --config configs/range-of-motion.json") from None
    if rom.anchors.ndim != 3 or rom.anchors.shape[0] != 21 or rom.anchors.shape[2] != 4 or rom.radius.shape != (21,):
        raise ValueError(f"{path}: range of motion has shapes {tuple(rom.anchors.shape)} / {tuple(rom.radius.shape)}, "
                         "expected (21, K, 4) / (21,)")
    if not (torch.isfinite(rom.anchors).all() and torch.isfinite(rom.radius).all() and (rom.radius >= 0).all()):
        raise ValueError(f"{path}: range of motion holds non-finite or negative values; rebuild it")
    rom.anchors = rot.normalize(rom.anchors)
    return rom
