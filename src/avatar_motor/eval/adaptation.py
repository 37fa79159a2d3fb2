"""Evaluation of adaptation (supplementary §9.3, Tables A3 and A4).

- A contrastive motion/label encoder (§9.3.1: transformer, 4 blocks, 256 wide, 8 heads; the
  label encoder is one embedding layer) trained on the adaptation data; top-1 R-precision is the
  fraction of generated motions whose nearest label embedding is the commanded label.
- `eval actions`: 3-s rollouts per label from held-out initial states, for every adaptor given.
- `eval reach`: 2-s rollouts to targets at (+-1.5, 0), (0, +-1.5), (+-1, 0), (0, +-1) m relative to
  the initial pelvis (in its body frame); minimal pelvis distance to the target (PRIMAL's), and
  the distance at the end (ours: an avatar that overshoots scores well on the first only).
"""
from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from ..data.dataset import SegmentDataset
from ..io.atomic import write_file
from ..body.motion_state import FPS, SLICES, canonicalize, joints_of
from ..model.checkpoint import Motor
from ..runtime.crowd import RuntimeConfig
from . import metrics as M
from .realism import rollout

TARGETS = [(1.5, 0.0), (-1.5, 0.0), (0.0, 1.5), (0.0, -1.5), (1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0)]


class MotionEncoder(nn.Module):
    """Canonical joint positions (B, T, 66) -> unit embedding (B, width). Reads every STRIDE-th frame
    (10 fps): actions differ over tenths of a second, and a third of the tokens trains 3x faster on CPU."""
    STRIDE = 3

    def __init__(self, frames: int, width: int = 256, depth: int = 4, heads: int = 8):
        super().__init__()
        self.frames = frames
        self.inp = nn.Linear(66, width)
        self.pos = nn.Parameter(torch.randn(1, -(-frames // self.STRIDE) + 1, width) * 0.02)
        self.cls = nn.Parameter(torch.zeros(1, 1, width))
        layer = nn.TransformerEncoderLayer(width, heads, 4 * width, dropout=0.1, batch_first=True, norm_first=True)
        self.enc = nn.TransformerEncoder(layer, depth, enable_nested_tensor=False)
        self.out = nn.Linear(width, width)

    def forward(self, J: torch.Tensor) -> torch.Tensor:
        J = J[:, ::self.STRIDE]
        h = torch.cat((self.cls.expand(len(J), -1, -1), self.inp(J)), 1) + self.pos[:, : J.shape[1] + 1]
        return F.normalize(self.out(self.enc(h)[:, 0]), dim=-1)


class LabelEncoder(nn.Module):
    def __init__(self, n: int, width: int = 256):
        super().__init__()
        self.embed = nn.Embedding(n, width)

    def forward(self, y: torch.Tensor) -> torch.Tensor:
        return F.normalize(self.embed(y), dim=-1)


def canonical_joints(X: torch.Tensor) -> torch.Tensor:
    """World states (B, T, 267) -> joint positions (B, T, 66) in the first frame's canonical frame."""
    xc, _ = canonicalize(X.double())
    return xc[..., SLICES["joints"]].float()


def train_encoder(ds: SegmentDataset, label_key: str, classes: list[str], seconds: float = 3.0, steps: int = 600,
                  seed: int = 0, progress=None) -> tuple[MotionEncoder, LabelEncoder]:
    """Contrastive training (CLIP-style, temperature 0.07) on windows of the labelled data."""
    g = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    T = int(seconds * FPS)
    if ds.cfg.frames + 1 < T:
        raise ValueError(f"the dataset's windows ({ds.cfg.frames + 1} frames) are shorter than {T}")
    menc, lenc = MotionEncoder(T), LabelEncoder(len(classes))
    opt = torch.optim.AdamW(list(menc.parameters()) + list(lenc.parameters()), lr=3e-4)
    index = {c: k for k, c in enumerate(classes)}
    for step in range(steps):
        x, _, clip = ds.sample_indexed(64, g)
        y = torch.tensor([index[ds.clip_labels[int(k)][label_key]] for k in clip])
        logits = menc(x[:, :T, SLICES["joints"]]) @ lenc(torch.arange(len(classes))).T / 0.07
        loss = F.cross_entropy(logits, y)
        opt.zero_grad()
        loss.backward()
        opt.step()
        if progress and (step + 1) % 250 == 0:
            progress(f"encoder step {step + 1}: loss {loss.item():.3f}")
    return menc.eval(), lenc.eval()


def _evaluator_source(ds: SegmentDataset, label_key: str, classes: list[str], seconds: float, steps: int) -> dict:
    """What an evaluator is trained from, but its seed: the clips (names, lengths, a checksum of
    their motion), labels, window length and steps."""
    return {"format": 1, "label_key": label_key, "classes": classes, "seconds": seconds, "steps": steps,
            "clips": [[n, int(k)] for n, k in zip(ds.clip_names, ds.clip_len)],
            "motion": round(float(ds.root_pos.double().abs().sum()), 3)}


def train_evaluators(ds: SegmentDataset, label_key: str, classes: list[str], seconds: float, steps: int,
                     seeds: list[int], progress=None, cache: Path | None = None) -> list[tuple[MotionEncoder, LabelEncoder]]:
    """One evaluator per seed. A single one, overfit to a few clips, reads borderline generated
    motion by its own quirks (R-precision moved by 0.013 with the thread count it trained on), so
    `eval actions --evaluators N` reports the mean and range over N of them. With `cache` (a
    folder) each evaluator is trained once and read back after: methods evaluated on different
    days or thread counts are then read by the same evaluators."""
    say = progress or (lambda m: None)
    source = _evaluator_source(ds, label_key, classes, seconds, steps) if cache else None
    out = []
    for s in seeds:
        key = hashlib.sha256(json.dumps({**source, "seed": s}, sort_keys=True).encode()).hexdigest()[:16] if cache else ""
        path = cache / f"{key}.pt" if cache else None
        if path is not None and path.exists():
            try:
                saved = torch.load(path, weights_only=True)
                menc, lenc = MotionEncoder(saved["frames"]), LabelEncoder(len(classes))
                menc.load_state_dict(saved["motion"])
                lenc.load_state_dict(saved["label"])
                out.append((menc.eval(), lenc.eval()))
                say(f"evaluator seed {s}: {path}")
                continue
            except Exception as e:  # a damaged file is replaced, never trusted
                say(f"evaluator seed {s}: {path} is unreadable ({type(e).__name__}: {e}); training it again")
        say(f"evaluator seed {s}: training")
        menc, lenc = train_encoder(ds, label_key, classes, seconds, steps, s, progress)
        out.append((menc, lenc))
        if path is not None:
            state = {"frames": menc.frames, "motion": menc.state_dict(), "label": lenc.state_dict(),
                     "threads": torch.get_num_threads()}
            write_file(path, lambda tmp, state=state: torch.save(state, tmp))
    return out


@torch.no_grad()
def embed(menc: MotionEncoder, X: torch.Tensor, canonical: bool = False) -> torch.Tensor:
    """The motion encoder's features (B, d) of motions X: world states (B, T, 267), or canonical
    windows if `canonical`."""
    J = X[..., SLICES["joints"]].float() if canonical else canonical_joints(X)
    return menc(J[:, :menc.frames])


@torch.no_grad()
def predict_labels(menc: MotionEncoder, lenc: LabelEncoder, X: torch.Tensor, canonical: bool = False) -> torch.Tensor:
    """The evaluator's label for motions X: world states (B, T, 267), or canonical windows if `canonical`."""
    return (embed(menc, X, canonical) @ lenc(torch.arange(lenc.embed.num_embeddings)).T).argmax(-1)


def r_precisions(encoders: list, X: torch.Tensor, y: torch.Tensor, canonical: bool = False) -> dict:
    """Top-1 R-precision (the fraction of motions whose nearest label embedding is y) by each
    evaluator: their mean, min and max, and the confusion matrix averaged over them (commanded
    rows, recognised columns)."""
    n = encoders[0][1].embed.num_embeddings
    rs, conf = [], torch.zeros(n, n)
    for menc, lenc in encoders:
        pred = predict_labels(menc, lenc, X, canonical)
        rs.append(float((pred == y).float().mean()))
        conf.index_put_((y, pred), torch.ones(len(y)), accumulate=True)
    return {"R_precision": sum(rs) / len(rs), "R_min": min(rs), "R_max": max(rs), "confusion": (conf / len(encoders)).tolist()}


def _rollout(motor: Motor, adaptor, init, shapes, frames: int, setup, seed: int, cfg: RuntimeConfig) -> torch.Tensor:
    """A rollout whose avatar k gets setup(crowd, avatar id, k) before the first segment."""
    def controls(crowd, seg):
        if seg == 0:
            for k, i in enumerate(sorted(crowd.avatars)):
                setup(crowd, i, k)
    return rollout(motor, init, shapes, frames, cfg, seed, controls, adaptor)


def eval_actions(motor: Motor, adaptors: dict, encoders: list, init, shapes, classes: list[str], seconds: float = 3.0,
                 seed: int = 0, cfg: RuntimeConfig | None = None, scale: float | None = None) -> tuple[list[dict], dict]:
    """Rows of Table A3 (a method named "base" with adaptor None is the unadapted model), read by
    each of `encoders` (see r_precisions), and the rollouts {method: {label: (n, T, 267)}}."""
    cfg = cfg or RuntimeConfig()
    rows, rollouts = [], {}
    for name, ad in adaptors.items():
        Xs, ys, per_label = [], [], {}
        for c, label in enumerate(classes):
            setup = (lambda crowd, i, k, label=label: crowd.set_label(i, label, scale)) if ad is not None else (lambda *_: None)
            X = _rollout(motor, ad, init, shapes, int(seconds * FPS), setup, seed, cfg)
            Xs.append(X)
            ys.append(torch.full((len(X),), c))
            per_label[label] = X
        X, y = torch.cat(Xs), torch.cat(ys)
        rollouts[name] = per_label
        rows.append({"method": name, **r_precisions(encoders, X, y), "ASR": M.asr(joints_of(X)), "ANCR": M.ancr(joints_of(X))})
    return rows, rollouts


def eval_reach(motor: Motor, adaptors: dict, init, shapes, seconds: float = 2.0, seed: int = 0,
               cfg: RuntimeConfig | None = None, scale: float | None = None) -> tuple[list[dict], dict]:
    """Rows of Table A4 (with each target's mean minimal distance, in TARGETS' order) and the
    pelvis paths {method: (8 targets, n, T, 2)} in each initial state's own frame (x left, z
    forward), where the targets are TARGETS."""
    from ..body.motion_state import canonical_transform
    cfg = cfg or RuntimeConfig()
    tf = canonical_transform(init.double())
    rows, paths = [], {}
    for name, ad in adaptors.items():
        dists, finals, Js, local = [], [], [], []
        for tx, tz in TARGETS:
            world = (tf.R.float() @ torch.tensor([tx, 0.0, tz]) + tf.t.float())[:, [0, 2]]  # (n, 2)
            setup = (lambda crowd, i, k, world=world: crowd.set_target(i, world[k].tolist(), scale)) if ad is not None else (lambda *_: None)
            X = _rollout(motor, ad, init, shapes, int(seconds * FPS), setup, seed, cfg)
            J = joints_of(X)
            d = (J[:, :, 0, [0, 2]] - world[:, None]).norm(dim=-1)
            dists.append(d.amin(1))
            finals.append(d[:, -1])  # where it ends up: a body that walks through the target is not there
            Js.append(J)
            pel = J[:, :, 0].double() - tf.t[:, None]
            local.append((pel @ tf.R)[..., [0, 2]].float())  # R^T p per frame
        J = torch.cat(Js)
        paths[name] = torch.stack(local)
        rows.append({"method": name, "min_dist_m": float(torch.cat(dists).mean()), "final_dist_m": float(torch.cat(finals).mean()),
                     "ASR": M.asr(J), "ANCR": M.ancr(J),
                     # per target: a run can reach one side well and the other not (a seed of the
                     # shipped recipe read 0.02 m to the right and 0.12 m to the left)
                     "per_target_m": [float(d.mean()) for d in dists]})
    return rows, paths


# the bound on foot skating a reaching adaptor is held to (PRIMAL Table A4: ASR 0.068 for ours, the
# issue's goal 0.070)
REACH_ASR_BOUND = 0.070


def best_reaching(rows: list[dict], asr_bound: float = REACH_ASR_BOUND) -> tuple[dict, bool]:
    """The row (of eval_reach, the base's aside) that comes nearest its targets among those that
    skate within asr_bound, and whether any did (if none, the nearest of all). Used to choose
    between training seeds, on initial states other than those the figures are reported on: runs
    of one recipe settle in different places (five runs: 0.024-0.045 m on the same 45 states)."""
    runs = [r for r in rows if r["method"] != "base" and math.isfinite(r["min_dist_m"]) and math.isfinite(r["ASR"])]
    if not runs:
        raise ValueError("choosing the best reaching adaptor needs at least one adaptor besides the base "
                         "whose figures are finite")
    within = [r for r in runs if r["ASR"] <= asr_bound]
    return min(within or runs, key=lambda r: r["min_dist_m"]), bool(within)


def format_confusion(rows: list[dict], classes: list[str]) -> str:
    """Per method: how many rollouts of each commanded label (row) the evaluators read as each label
    (on average over them)."""
    out = []
    for r in rows:
        if r["method"] == "base":
            continue  # the base ignores labels: its rows are all alike
        out.append(f"{r['method']}: commanded (rows) vs recognised (columns)")
        out.append(f"{'':12s} " + " ".join(f"{c[:9]:>9s}" for c in classes))
        whole = all(float(v).is_integer() for row in r["confusion"] for v in row)  # one evaluator: counts
        out += [f"{c[:12]:12s} " + " ".join(f"{v:9.0f}" if whole else f"{v:9.1f}" for v in row)
                for c, row in zip(classes, r["confusion"])]
    return "\n".join(out)


def format_rows(title: str, rows: list[dict], keys: list[str]) -> str:
    w = max([14] + [len(r["method"]) for r in rows])
    out = [title, f"{'method':{w}s} " + " ".join(f"{k:>12s}" for k in keys)]
    for r in rows:
        out.append(f"{r['method']:{w}s} " + " ".join(f"{r[k]:12.3f}" if not math.isnan(r[k]) else f"{'nan':>12s}" for k in keys))
    return "\n".join(out)
