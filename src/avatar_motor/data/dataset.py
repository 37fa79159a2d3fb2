"""SegmentDataset: canonicalized windows of 1 initial state + N frames, drawn from motion caches.

Each sample: pick a clip and a start frame, take N+2 frames (one extra in front so the initial
state's backward velocity is real), draw a random body shape (PRIMAL trains with random beta),
scale the root trajectory by the shape's leg length (MotionPersona Eq. 3), optionally mirror
left/right, run the one FK, and canonicalize on the initial state. All batched in torch.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..body import rotations as rot
from ..body.skeleton import MIRROR, SHAPE_DIM, forward_kinematics, pelvis_height, random_shapes, rest_offsets
from ..io.atomic import write_file
from .cache import MotionCache, is_held_out
from ..body.motion_state import FPS, STATE_DIM, canonicalize, finite_velocities, pack

_M = torch.diag(torch.tensor([-1.0, 1.0, 1.0]))


@dataclass
class SegmentConfig:
    frames: int = 15  # generated frames per segment (plus 1 initial state)
    shape_augment: float = 1.0  # std of random body-shape vectors (0 = average body only)
    mirror: bool = True
    split: str = "train"  # "train", "heldout" or "all"
    # share of the windows drawn from a cache, by cache name (e.g. {"deepmimic": 0.1}), or from the
    # clips of a cache whose file names contain a text ("deepmimic/kick"; these are taken out of
    # their cache's share); the windows not named share the rest in proportion to their number.
    # Default: every window alike.
    weights: dict[str, float] = field(default_factory=dict)


class SegmentDataset:
    def __init__(self, caches: list[MotionCache], cfg: SegmentConfig | None = None, clip_filter=None):
        """clip_filter(clip metadata) -> bool keeps only some clips (e.g. chosen action classes)."""
        self.cfg = cfg or SegmentConfig()
        need = self.cfg.frames + 2
        roots, quats, starts, lens, names, labels = [], [], [], [], [], []
        offset = 0
        clip_cache = []
        for c, cache in enumerate(caches):
            for i, clip in enumerate(cache.clips):
                held = is_held_out(clip["key"])
                if (self.cfg.split == "train" and held) or (self.cfg.split == "heldout" and not held):
                    continue
                if clip_filter is not None and not clip_filter(clip):
                    continue
                rp, q = cache.clip(i)
                if rp.shape[0] < need:
                    continue
                roots.append(rp)
                quats.append(q)
                starts.append(offset)
                lens.append(rp.shape[0])
                names.append(clip["key"])
                labels.append(clip.get("labels", {}))
                clip_cache.append(c)
                offset += rp.shape[0]
        if not roots:
            raise ValueError(f"no clip of at least {need} frames in split {self.cfg.split!r}; import more motion")
        self.root_pos = torch.from_numpy(np.concatenate(roots))
        self.rotmats = rot.quat_to_matrix(torch.from_numpy(np.concatenate(quats)))  # (N, 22, 3, 3)
        self.clip_start = torch.tensor(starts)
        self.clip_len = torch.tensor(lens)
        self.clip_names = names
        self.clip_labels = labels
        # every valid window start, weighted uniformly over frames, and the clip it belongs to
        self.window_starts = torch.cat([torch.arange(s, s + n - need + 1) for s, n in zip(starts, lens)])
        self.window_clip = torch.cat([torch.full((n - need + 1,), k) for k, n in enumerate(lens)])
        self.window_cdf = _window_cdf([c.meta.get("name") or Path(str(c.path)).stem for c in caches], clip_cache, names,
                                      self.window_clip, self.cfg.weights)

    def __len__(self) -> int:
        return len(self.window_starts)

    @property
    def frames_total(self) -> int:
        return int(self.clip_len.sum())

    def sample(self, batch: int, generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(states (B, 1+N, 267) canonical, shapes (B, SHAPE_DIM)), random windows."""
        return self.sample_indexed(batch, generator)[:2]

    def sample_indexed(self, batch: int, generator: torch.Generator | None = None):
        """Like sample, plus the index of each window's clip (for its labels)."""
        if self.window_cdf is None:
            idx = torch.randint(len(self.window_starts), (batch,), generator=generator)
        else:
            u = torch.rand(batch, generator=generator, dtype=torch.float64)
            idx = torch.searchsorted(self.window_cdf, u, right=True).clamp(max=len(self.window_starts) - 1)
        x, shapes = self.windows(self.window_starts[idx], generator)
        return x, shapes, self.window_clip[idx]

    def windows(self, starts: torch.Tensor, generator: torch.Generator | None = None,
                shapes: torch.Tensor | None = None, mirror: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        cfg = self.cfg
        B, T = len(starts), cfg.frames + 2
        fr = starts[:, None] + torch.arange(T)
        root = self.root_pos[fr].double()
        R = self.rotmats[fr].double()
        if shapes is None:
            shapes = random_shapes(B, generator, cfg.shape_augment) if cfg.shape_augment > 0 else torch.zeros(B, SHAPE_DIM)
        if mirror is None:
            mirror = (torch.rand(B, generator=generator) < 0.5) if cfg.mirror else torch.zeros(B, dtype=torch.bool)
        if mirror.any():
            M = _M.double()
            root_m = root * torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64)
            R_m = (M @ R @ M)[:, :, MIRROR]
            root = torch.where(mirror[:, None, None], root_m, root)
            R = torch.where(mirror[:, None, None, None, None], R_m, R)
        off = rest_offsets(shapes, torch.float64)  # (B, 22, 3)
        ratio = pelvis_height(off) / pelvis_height(rest_offsets(None, torch.float64))
        root = root * ratio[:, None, None]
        J, _ = forward_kinematics(root, R[:, :, 0], R[:, :, 1:], off[:, None])
        vel = finite_velocities(J, FPS)[:, 1:]
        x = pack(root[:, 1:], R[:, 1:, 0], R[:, 1:, 1:], J[:, 1:], vel)
        xc, _ = canonicalize(x)
        return xc.float(), shapes.float()


def _window_cdf(cache_names: list[str], clip_cache: list[int], clip_keys: list[str], window_clip: torch.Tensor,
                weights: dict[str, float]) -> torch.Tensor | None:
    """Cumulative draw probability of each window (None: uniform) for `SegmentConfig.weights`: the
    windows of each named group (a cache, or "cache/text": its clips whose file names hold the
    text, which leave their cache's group) share its weight, the rest share what is left, each
    window of a group alike."""
    if not weights:
        return None
    if any(not 0 < w <= 1 for w in weights.values()):
        raise ValueError(f"segment.weights must be shares in (0, 1], got {weights}")
    keys = list(weights)
    unknown = sorted(k for k in keys if k.split("/", 1)[0] not in cache_names)
    if unknown:
        raise ValueError(f"segment.weights names {unknown}, which the training data lacks; its caches are {cache_names}")

    def group(c: int) -> int:  # a clip's weights key (the more specific first), or -1
        cache, name = cache_names[clip_cache[c]], Path(clip_keys[c]).name
        for k, key in enumerate(keys):
            if "/" in key and key.split("/", 1)[0] == cache and key.split("/", 1)[1] in name:
                return k
        return keys.index(cache) if cache in keys else -1

    win_group = torch.tensor([group(c) for c in range(len(clip_keys))])[window_clip]
    counts = torch.stack([(win_group == k).sum() for k in range(-1, len(keys))]).double()  # [rest, key 0, ...]
    empty = [key for key, n in zip(keys, counts[1:]) if n == 0]
    if empty:
        raise ValueError(f"segment.weights names {empty}, which has no window of this split; drop it from the weights")
    rest = 1.0 - sum(weights.values())
    if rest < -1e-9 or (rest > 1e-9 and counts[0] == 0):
        raise ValueError(f"segment.weights {weights} must sum to 1 over the caches {cache_names} when all are named, "
                         "and below 1 when some are not")
    share = torch.tensor([max(rest, 0.0), *weights.values()], dtype=torch.float64)
    p = share[win_group + 1] / counts[win_group + 1]
    cdf = torch.cumsum(p, 0)
    return cdf / cdf[-1]


@dataclass
class Normalizer:
    """Per-dimension mean and std of canonical states (std floored so constant dims stay finite)."""
    mean: torch.Tensor
    std: torch.Tensor

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.mean) / self.std

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        return z * self.std + self.mean

    def to_dict(self) -> dict:
        return {"mean": self.mean.tolist(), "std": self.std.tolist()}

    @staticmethod
    def from_dict(d: dict) -> "Normalizer":
        mean, std = torch.tensor(d["mean"], dtype=torch.float32), torch.tensor(d["std"], dtype=torch.float32)
        if (mean.shape != (STATE_DIM,) or std.shape != (STATE_DIM,) or (std <= 0).any()
                or not (torch.isfinite(mean).all() and torch.isfinite(std).all())):
            raise ValueError(f"normalisation statistics must be {STATE_DIM} finite means and positive stds")
        return Normalizer(mean, std)

    @staticmethod
    def compute(ds: SegmentDataset, n: int = 20000, seed: int = 0) -> "Normalizer":
        g = torch.Generator().manual_seed(seed)
        n = min(n, max(2000, 10 * len(ds)))  # a small dataset needs fewer draws to be covered
        xs = torch.cat([ds.sample(min(2000, n), g)[0].reshape(-1, STATE_DIM) for _ in range(max(1, n // 2000))])
        return Normalizer(xs.mean(0), xs.std(0).clamp_min(1e-2))


def stats_path(cache_paths: list[Path]) -> Path:
    """Statistics live next to the first cache, keyed by the set of caches they cover."""
    names = "+".join(sorted(Path(p).stem for p in cache_paths))
    return Path(cache_paths[0]).with_name(f"{names}.stats.json")


def _fingerprint(cache_paths: list[Path]) -> list[list]:
    """What the statistics were computed from: a re-imported cache changes its size or time."""
    stats = [(Path(p).name, Path(p).stat()) for p in sorted(cache_paths)]
    return [[name, st.st_size, st.st_mtime_ns] for name, st in stats]


def load_or_compute_stats(ds: SegmentDataset, cache_paths: list[Path]) -> Normalizer:
    p = stats_path(cache_paths)
    # the windows' weights change what the statistics cover (they are drawn as training draws)
    sources = _fingerprint(cache_paths) + ([["weights", ds.cfg.weights]] if ds.cfg.weights else [])
    if p.exists():
        try:
            d = json.loads(p.read_text())
            if d.get("sources") == sources:
                return Normalizer.from_dict(d)
        except (ValueError, json.JSONDecodeError):
            pass  # recompute below and overwrite the bad or stale file
    norm = Normalizer.compute(ds)
    write_file(p, lambda tmp: tmp.write_text(json.dumps({**norm.to_dict(), "sources": sources})))
    return norm
