"""Adaptation of a frozen base denoiser to a control signal (PRIMAL §4, Fig. 3).

Three methods, as compared in PRIMAL's Tables A3/A4:
- "controlnet" (PRIMAL's): a trainable copy of every transformer block; the control embedding
  is added to the previous block's output before it enters the copy, and the copy's output
  returns through a zero-initialised projection into the base stream. Base frozen.
- "omni" (OmniControlNet-style): the same copies, but the control is fused once, at the input
  of a chain of copies. Base frozen.
- "finetune": the control embedding is added to the time embedding and the whole base trains.
The control is an action label (embedding layer, with a null label for classifier-free
dropout) or a 2-D target (linear embedding; a mask stands for "no target").
`scale` from 0 to 1 multiplies the adaptor's residuals: 0 gives the base model exactly, 1 the
trained adaptor; above 1 it is a guidance weight: of Eq. 3 against the null control (PRIMAL's), or
for labels (the default) against the nearest other label (see _negative).
Adaptor weights are saved on their own (safetensors + JSON), so many adaptors share one base.
"""
from __future__ import annotations

import copy
import hashlib
import json
import math
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file
from torch import nn

from ..io.atomic import replace_folder
from .denoiser import Denoiser

ADAPTOR_FORMAT = "avatar-motor-adaptor/1"
KINDS = ("controlnet", "omni", "finetune")
CONTROLS = ("label", "target")


@dataclass
class AdaptorConfig:
    kind: str = "controlnet"
    control: str = "label"
    labels: list[str] = field(default_factory=list)  # for control == "label"
    control_dropout: float = 0.1  # probability of training with the null control (CFG)

    def validate(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"adaptor kind must be one of {KINDS}, got {self.kind!r}")
        if self.control not in CONTROLS:
            raise ValueError(f"adaptor control must be one of {CONTROLS}, got {self.control!r}")
        if not isinstance(self.labels, list) or len(self.labels) > 1000 or not all(isinstance(x, str) for x in self.labels):
            raise ValueError(f"adaptor labels must be a list of at most 1000 strings, got {str(self.labels)[:100]}")
        if self.control == "label" and len(self.labels) < 1:
            raise ValueError("a label adaptor needs at least one label")


def rescale_target(xz: torch.Tensor) -> torch.Tensor:
    """PRIMAL's target encoding: 2(1 - exp(-|x|)) x/|x| (bounded, fine near the body)."""
    n = xz.norm(dim=-1, keepdim=True)
    return 2 * (1 - torch.exp(-n)) * xz / n.clamp_min(1e-6)


class AdaptedDenoiser(nn.Module):
    def __init__(self, base: Denoiser, cfg: AdaptorConfig):
        super().__init__()
        cfg.validate()
        self.cfg = cfg
        self.guidance = "nearest"  # what a scale above 1 steers away from: "nearest" or "null" (see _negative)
        self.name = "adaptor"  # what a client shows it as: its folder's name once loaded
        # the control scale its avatars get when a command names none: the one its card measures
        # (adaptor.json "scale", set by `ship --scale`; 1 = as trained)
        self.default_scale = 1.0
        # which base weights this adaptor starts from, taken before any training changes them
        self.base_fingerprint = base_fingerprint(base)
        # fine-tuning trains the base itself: on a copy, so the shared base model (the runtime's
        # avatars without a label, the other methods of an eval) stays as it is
        self.base = copy.deepcopy(base) if cfg.kind == "finetune" else base
        w = base.cfg.width
        if cfg.control == "label":
            self.embed = nn.Embedding(len(cfg.labels) + 1, w)  # the last index is the null label
        else:
            self.embed = nn.Linear(2, w)
        if cfg.kind in ("controlnet", "omni"):
            self.copies = copy.deepcopy(base.blocks)
            self.zero = nn.ModuleList(nn.Linear(w, w) for _ in base.blocks)
            for z in self.zero:
                nn.init.zeros_(z.weight)
                nn.init.zeros_(z.bias)
            for p in self.base.parameters():
                p.requires_grad_(False)

    @property
    def null_label(self) -> int:
        return len(self.cfg.labels)

    def control_embedding(self, y: torch.Tensor, drop: torch.Tensor | None = None) -> torch.Tensor:
        """y: (B,) long labels or (B, 2) canonical targets; drop (B,) bool selects the null control."""
        if self.cfg.control == "label":
            if drop is not None:
                y = torch.where(drop, torch.full_like(y, self.null_label), y)
            return self.embed(y)
        e = self.embed(rescale_target(y))
        return e if drop is None else e * (~drop)[:, None].float()

    def forward(self, t, x_t, x0, y, scale: float | torch.Tensor = 1.0, drop: torch.Tensor | None = None) -> torch.Tensor:
        """scale (a number or one per row, (B, 1, 1)): from 0 (the base model) to 1 (the trained
        adaptor) the adaptor's residuals are scaled; above 1 it is the guidance weight gamma:
        G(y) + (gamma - 1) (G(y) - N), with N the null control's prediction (Eq. 3, control dropout
        trained it) or the nearest other label's (see _negative): one more pass, for the rows that ask for it."""
        s = torch.as_tensor(scale, dtype=x_t.dtype).reshape(-1, 1, 1).expand(len(x_t), 1, 1)
        guided = (s > 1).flatten()
        if guided.any() and self._null_negative:
            # the null control's pass in the same batch as the rows' own: one network call (a
            # reaching avatar's 4 candidates at 8 steps: 38 -> 28 ms a step here, batch 4 + 4)
            r, B = guided.nonzero()[:, 0], len(t)
            d = torch.zeros(B, dtype=torch.bool) if drop is None else drop
            both = self._forward(torch.cat((t, t[r])), torch.cat((x_t, x_t[r])), torch.cat((x0, x0[r])),
                                 torch.cat((y, y[r])), torch.cat((s.clamp(max=1.0), torch.ones_like(s[r]))),
                                 torch.cat((d, torch.ones(len(r), dtype=torch.bool))))
            out = both[:B].clone()
            out[r] = out[r] + (s[r] - 1) * (out[r] - both[B:])
            return out
        out = self._forward(t, x_t, x0, y, s.clamp(max=1.0), drop)
        if guided.any():
            r = guided.nonzero()[:, 0]
            out = out.clone()
            out[r] = out[r] + (s[r] - 1) * (out[r] - self._negative(t[r], x_t[r], x0[r], y[r], out[r]))
        return out

    def scale_for(self, scale: float | None) -> float:
        """The control scale a command gets: its own, or (None) this adaptor's default_scale."""
        return self.default_scale if scale is None else scale

    @property
    def _null_negative(self) -> bool:
        """Guidance steers away from the null control (_negative)."""
        if self.guidance not in ("nearest", "null"):
            raise ValueError(f"adaptor guidance must be 'nearest' or 'null', not {self.guidance!r}")
        return self.guidance == "null" or self.cfg.control != "label" or len(self.cfg.labels) < 2

    def _negative(self, t, x_t, x0, y, cond: torch.Tensor) -> torch.Tensor:
        """What guidance steers away from: the null control (PRIMAL's Eq. 3), or with guidance
        "nearest" (label adaptors) the prediction of the other label nearest to this label's own
        `cond`, per row and step (the others in one batched pass). Our addition: the null control
        continues the current state while a label turns it into the action, so G(y) - G(null) also
        holds that departure and amplifying it slides the feet; every label departs alike, so the
        difference to the closest rival holds what tells y from the label it would be taken for."""
        if self._null_negative:
            return self._forward(t, x_t, x0, y, 1.0, torch.ones(len(t), dtype=torch.bool))
        n, B = len(self.cfg.labels), len(t)
        others = (y[:, None] + torch.arange(1, n)[None]).remainder(n).flatten()  # (B * (n - 1),)
        rep = lambda v: v.repeat_interleave(n - 1, 0)  # noqa: E731
        pred = self._forward(rep(t), rep(x_t), rep(x0), others, 1.0, None).view(B, n - 1, *cond.shape[1:])
        nearest = (pred - cond[:, None]).square().flatten(2).sum(-1).argmin(1)
        return pred[torch.arange(B), nearest]

    def _forward(self, t, x_t, x0, y, scale, drop: torch.Tensor | None) -> torch.Tensor:
        base = self.base
        cond = base.condition(t, x0)
        e = self.control_embedding(y, drop)
        if self.cfg.kind == "finetune":
            # scale: a number or one per row (B, 1, 1) as the runtime passes it
            cond = cond + (scale.reshape(-1, 1) if torch.is_tensor(scale) else scale) * e
            h = base.tokens(base.blended(x_t, x0), cond)
            for blk in base.blocks:
                h = blk(h, cond)
            return base.head(h)
        h = base.tokens(base.blended(x_t, x0), cond)
        c = h
        for i, blk in enumerate(base.blocks):
            if self.cfg.kind == "controlnet":
                c = self.copies[i](h + e[:, None], cond)
            else:  # omni: the control enters once, the copies form their own chain
                c = self.copies[i](c + e[:, None] if i == 0 else c, cond)
            h = blk(h, cond) + scale * self.zero[i](c)
        return base.head(h)

    def adaptor_state(self) -> dict[str, torch.Tensor]:
        """The weights that belong to the adaptor (for finetune: the whole tuned network)."""
        return {k: v for k, v in self.state_dict().items() if self.cfg.kind == "finetune" or not k.startswith("base.")}


def base_fingerprint(net: Denoiser) -> str:
    """Identifies the base weights an adaptor was trained on (a retrained base keeps its name).
    Taken over float16 values, so a training checkpoint and its shipped float16 copy agree."""
    h = hashlib.sha1()
    for k, v in sorted(net.state_dict().items()):
        h.update(k.encode())
        h.update(v.detach().to(torch.float16).contiguous().numpy().tobytes())
    return h.hexdigest()[:16]


def _adaptor_complete(folder: Path) -> bool:
    """An adaptor folder whose files were all written (adaptor.json is written last)."""
    return (folder / "adaptor.safetensors").exists() and (folder / "adaptor.json").exists()


def save_adaptor(folder: str | Path, model: AdaptedDenoiser, base_name: str, info: dict | None = None,
                 card: str | None = None, half: bool = False) -> Path:
    """Write so that a kill at any instant leaves the old adaptor or the new one (io/atomic.py).
    half=True stores float16 weights (shipped adaptors; loading casts back to float32)."""
    meta = {"format": ADAPTOR_FORMAT, "adaptor": asdict(model.cfg), "base_model": base_name,
            "base_fingerprint": model.base_fingerprint, **(info or {})}
    dtype = torch.float16 if half else None

    def fill(tmp: Path) -> None:
        save_file({k: v.detach().to(dtype or v.dtype).contiguous() for k, v in model.adaptor_state().items()},
                  str(tmp / "adaptor.safetensors"))
        if card is not None:
            (tmp / "card.md").write_text(card)
        (tmp / "adaptor.json").write_text(json.dumps(meta, indent=1))

    return replace_folder(folder, fill, _adaptor_complete)


def ship_adaptor(src: str | Path, dst: str | Path, base, card: str, scale: float | None = None) -> Path:
    """Copy a trained adaptor (on the loaded base Motor `base`) into a shippable one: float16
    weights, its card, named for its folder; `scale` its avatars' default control scale (None:
    the source's)."""
    src = Path(src)
    model = load_adaptor(src, base.net, base.name)
    meta = json.loads((src / "adaptor.json").read_text())
    info = {k: v for k, v in meta.items() if k not in ("format", "adaptor", "base_model", "base_fingerprint")}
    info["name"] = Path(dst).name
    if scale is not None:
        info["scale"] = float(scale)
    return save_adaptor(dst, model, base.name, info, card, half=True)


def load_adaptor(folder: str | Path, base: Denoiser, base_name: str | None = None) -> AdaptedDenoiser:
    folder = Path(folder)
    try:
        meta = json.loads((folder / "adaptor.json").read_text())
        weights = load_file(str(folder / "adaptor.safetensors"))
    except Exception as e:  # noqa: BLE001 - any unreadable file gets the same clear message
        raise ValueError(f"{folder}: not a readable adaptor ({e}); pass a folder written by 'avatar-motor adapt'") from None
    if not isinstance(meta, dict) or not isinstance(meta.get("adaptor"), dict):
        raise ValueError(f"{folder}: adaptor.json must be an object with an 'adaptor' object; the adaptor is corrupt")
    if meta.get("format") != ADAPTOR_FORMAT:
        raise ValueError(f"{folder}: format {meta.get('format')!r} is not {ADAPTOR_FORMAT!r}")
    if base_name is not None and meta.get("base_model") != base_name:
        raise ValueError(f"{folder}: adaptor was trained on base model {meta.get('base_model')!r}, not {base_name!r}")
    if "base_fingerprint" not in meta:
        warnings.warn(f"{folder}: the adaptor does not record which base weights it was trained on (older format); "
                      "if the base was retrained since, retrain the adaptor", stacklevel=2)
    try:
        acfg = AdaptorConfig(**meta["adaptor"])
    except TypeError as e:
        raise ValueError(f"{folder}: invalid adaptor config ({e}); pass a folder written by 'avatar-motor adapt'") from None
    model = AdaptedDenoiser(base, acfg)  # takes the base's fingerprint
    if meta.get("base_fingerprint", model.base_fingerprint) != model.base_fingerprint:
        raise ValueError(f"{folder}: adaptor was trained on other weights of base model {meta.get('base_model')!r} "
                         "(the base was retrained since); retrain the adaptor with 'avatar-motor adapt' on this base")
    missing, unexpected = model.load_state_dict(weights, strict=False)
    expected = set(model.adaptor_state())
    if set(weights) != expected:
        raise ValueError(f"{folder}: adaptor weights do not match its config (missing {sorted(expected - set(weights))[:3]}, "
                         f"unexpected {sorted(set(weights) - expected)[:3]})")
    # runs/adapt-actions/adaptor is named for its run, models/primal-bandai-actions for itself
    model.name = str(meta.get("name") or (folder.resolve().parent.name if folder.name == "adaptor" else folder.name))
    scale = meta.get("scale", 1.0)
    if not (isinstance(scale, (int, float)) and math.isfinite(scale) and 0 <= scale <= 10):
        raise ValueError(f"{folder}: adaptor.json's scale must be a number in [0, 10], got {scale!r}; the adaptor is corrupt")
    model.default_scale = float(scale)
    return model.eval()


def shipped_adaptors(models: str | Path, base) -> list[Path]:
    """The adaptor folders under `models` (each holding adaptor.json) trained on this base's
    weights: the ones a command loads when it is given none. base: a loaded base Motor."""
    fp = base_fingerprint(base.net)
    out = []
    for meta_path in sorted(Path(models).glob("*/adaptor.json")):
        try:
            meta = json.loads(meta_path.read_text())
        except (OSError, json.JSONDecodeError):
            continue  # not ours to judge here: loading it by name gives the clear error
        if isinstance(meta, dict) and meta.get("base_fingerprint") == fp:
            out.append(meta_path.parent)
    return out


def default_adaptors(motor, models: str | Path) -> list[AdaptedDenoiser]:
    """The adaptors a command runs when it is given none: those under `models` trained on the
    motor's base (`shipped_adaptors`), loaded on that base. None when a few-step model's base is
    not beside it: no adaptor could run."""
    from .checkpoint import CheckpointError, load_base
    try:
        base = load_base(motor)  # a few-step model runs an adaptor's avatars on its base
    except CheckpointError:
        return []
    return [load_adaptor(folder, base.net, base.name) for folder in shipped_adaptors(models, base)]
