"""`eval persona` (MotionPersona Table 3, on our data): does the motion read as the described
character, does it follow the steered trajectory, and do the feet stay planted.

Characters are the Bandai dataset-2 styles; an evaluator trained on real clips of those styles
(eval/adaptation.py, the same one `eval actions --label-key style` uses) reads each rollout of the
exported body: CCA is its top-1 accuracy, R@3 the share whose style is among its three best.
Steered rollouts walk toward a goal velocity in the body's forward direction; TPE is the mean
distance (m) of the pelvis from the commanded path (the runtime's own goal_trajectory from the
start), TDE the mean angle (rad) between the body's facing and the goal's, after the first second.
With `settle` seconds, the rollouts run that much longer and the evaluator reads only the part
after it: the initial states are real held-out states of every style, shared by all the classes,
so from the first frame 6 in 7 rollouts begin as someone else and the evaluator reads the change
of character; after settling it reads the character as it goes on walking, as a spawned avatar
does in the studio (the real clips it is compared with have no such change).
`join` is the jerk across the segment joins over the jerk within segments (1: no seam).
FSD is foot sliding: the mean horizontal travel (cm per frame) of a foot joint while it is within
5 cm of the ground. FPD is the Fréchet distance of the read rollouts' evaluator features from
those of real held-out clips of the same styles (MotionPersona's FPD, with our evaluator as the
feature extractor; on about a hundred rollouts it is biased upward, so compare it within one
table), diversity the mean distance between two rollouts' features (real clips' in the header).
"""
from __future__ import annotations

import torch

from ..body.motion_state import FPS, canonical_transform, canonicalize, joints_of
from ..data.personas import descriptions
from ..runtime.crowd import RuntimeConfig
from ..runtime.guidance import facing_of, goal_trajectory
from . import metrics as M
from .adaptation import embed
from .realism import rollout


def top_k(encoders: list, X: torch.Tensor, y: torch.Tensor, k: int) -> float:
    """The share of motions X (world states) whose label y is among each evaluator's k best, averaged."""
    out = []
    with torch.no_grad():
        for (_, lenc), f in zip(encoders, features(encoders, X)):
            sim = f.float() @ lenc(torch.arange(lenc.embed.num_embeddings)).T
            best = sim.topk(k, dim=-1).indices
            out.append(float((best == y[:, None]).any(-1).float().mean()))
    return sum(out) / len(out)


def features(encoders: list, X: torch.Tensor, canonical: bool = False) -> list[torch.Tensor]:
    """Each evaluator's embedding (n, d) of motions X (`adaptation.embed`)."""
    return [embed(menc, X, canonical).double() for menc, _ in encoders]


def frechet(a: torch.Tensor, b: torch.Tensor) -> float:
    """The Fréchet distance between Gaussians fitted to feature sets a (n, d) and b (m, d):
    |mu_a - mu_b|^2 + tr(C_a + C_b - 2 (C_a^1/2 C_b C_a^1/2)^1/2)."""
    ca, cb = torch.cov(a.T), torch.cov(b.T)
    w, V = torch.linalg.eigh(ca)
    root = V @ torch.diag(w.clamp_min(0).sqrt()) @ V.T
    cross = torch.linalg.eigvalsh(root @ cb @ root).clamp_min(0).sqrt().sum()
    return float(((a.mean(0) - b.mean(0)) ** 2).sum() + ca.trace() + cb.trace() - 2 * cross)


def diversity(f: torch.Tensor) -> float:
    """The mean distance between two different motions' features f (n, d)."""
    d = torch.cdist(f, f)
    n = len(f)
    return float(d.sum() / (n * (n - 1)))


def fpd_div(encoders: list, X: torch.Tensor, real: list[torch.Tensor]) -> tuple[float, float]:
    """FPD (the Fréchet distance of motions X's evaluator features from the real held-out clips'
    `real`, one set per evaluator) and diversity, each averaged over the evaluators."""
    gen = features(encoders, X)
    return (sum(frechet(g, r) for g, r in zip(gen, real)) / len(gen), sum(diversity(g) for g in gen) / len(gen))


def fsd(J: torch.Tensor, height: float = 0.05) -> float:
    """Foot sliding: mean horizontal travel (cm per frame) of the foot joints while they are low."""
    f = J[..., M.FEET, :]
    step = (f[..., 1:, :, :] - f[..., :-1, :, :])[..., [0, 2]].norm(dim=-1)
    low = f[..., 1:, :, 1] < height
    return float(100 * step[low].mean()) if bool(low.any()) else 0.0


def trajectory_errors(X: torch.Tensor, goal: torch.Tensor) -> tuple[float, float]:
    """TPE (m) and TDE (rad) of world rollouts X (n, T, 267) steered at world goal velocities
    (n, 3) from their first frame; both over the frames after the first second."""
    T = X.shape[1]
    xc, tf = canonicalize(X[:, :1].double())  # the first frame in its own canonical frame, as the sampler sees it
    x0c, Rt = xc[:, 0], tf.R.transpose(-1, -2)
    g_c = (Rt @ goal.double()[..., None])[..., 0]
    f_c = g_c / g_c.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    path_c = goal_trajectory(x0c, g_c, f_c, T - 1)[..., :2]  # (n, T-1, 2) canonical x, z
    path = (tf.R[:, None] @ torch.stack((path_c[..., 0], torch.zeros_like(path_c[..., 0]), path_c[..., 1]), -1)[..., None])[..., 0]
    path = path + tf.t[:, None]
    pel = joints_of(X[:, 1:]).double()[:, :, 0]
    after = int(FPS)
    tpe = float((pel - path)[:, after:, [0, 2]].norm(dim=-1).mean())
    z, _ = facing_of(X[:, 1 + after:])
    r = (goal / goal.norm(dim=-1, keepdim=True))[:, None].to(z.dtype)
    cos = (z * r).sum(-1).clamp(-1, 1)
    return tpe, float(torch.acos(cos).mean())


def forward_goals(init: torch.Tensor, speed: float) -> torch.Tensor:
    """World goal velocities (n, 3): forward from each initial state (n, 267) at `speed` m/s."""
    return (canonical_transform(init.double()).R.float() @ torch.tensor([0.0, 0.0, 1.0])) * speed


def _controls(setup=None, goal: torch.Tensor | None = None):
    """Rollout controls: before the first segment, avatar k (in id order) gets setup(crowd, id, k)
    and, with `goal` (n, 3), the goal velocity goal[k]."""
    def controls(crowd, seg):
        if seg == 0:
            for k, i in enumerate(sorted(crowd.avatars)):
                if setup is not None:
                    setup(crowd, i, k)
                if goal is not None:
                    crowd.set_goal(i, (float(goal[k, 0]), float(goal[k, 2])))
    return controls


def _described(split: str):
    """setup(crowd, avatar, k, label): the k-th description of the label's split."""
    def setup(crowd, i, k, label):
        ds = descriptions(label, split)
        crowd.set_persona(i, ds[k % len(ds)])
    return setup


def methods_for(persona_motor, base_motor=None, styles_adaptor=None) -> dict:
    """The rows: name -> (motor, adaptor, setup(crowd, avatar id, k, label) or None)."""
    rows = {"persona, training descriptions": (persona_motor, None, _described("train")),
            "persona, unseen descriptions": (persona_motor, None, _described("heldout")),
            "persona, no description": (persona_motor, None, None)}
    if base_motor is not None and styles_adaptor is not None:
        rows["base + style adaptor"] = (base_motor, styles_adaptor, lambda crowd, i, k, label: crowd.set_label(i, label))
    if base_motor is not None:
        rows["base"] = (base_motor, None, None)
    return rows


def eval_persona(methods: dict, encoders: list, init: torch.Tensor, shapes: torch.Tensor, classes: list[str],
                 seconds: float = 3.0, seed: int = 0, cfg: RuntimeConfig | None = None, speed: float = 1.0,
                 settle: float = 0.0, real: list[torch.Tensor] | None = None) -> list[dict]:
    """One row per method: CCA and R@3 over the classes (unsteered rollouts, the `seconds` after
    `settle`); FSD, ASR and `join` (metrics.join_jerk: in-diffusion blending's own measure) over
    the whole of them; TPE/TDE of rollouts steered forward at `speed` m/s.
    With `real` (`features` of real held-out clips, one set per evaluator): FPD and diversity of
    the unsteered rollouts' read part too."""
    cfg = cfg or RuntimeConfig()
    s0 = int(settle * FPS)
    frames = s0 + int(seconds * FPS)
    goal = forward_goals(init, speed)
    rows = []
    for name, (motor, adaptor, setup) in methods.items():
        Xs, ys, Gs, joins = [], [], [], []
        for c, label in enumerate(classes):
            labelled = None if setup is None else (lambda crowd, i, k, label=label: setup(crowd, i, k, label))
            Xs.append(rollout(motor, init, shapes, frames, cfg, seed, _controls(labelled), adaptor, joins_out=joins))
            ys.append(torch.full((len(init),), c))
            Gs.append(rollout(motor, init, shapes, frames, cfg, seed, _controls(labelled, goal), adaptor))
        X, y, G = torch.cat(Xs), torch.cat(ys), torch.cat(Gs)
        tpe, tde = trajectory_errors(G, goal.repeat(len(classes), 1))
        J = joints_of(X)
        rows.append({"method": name, "CCA": top_k(encoders, X[:, s0:], y, 1), "R@3": top_k(encoders, X[:, s0:], y, 3),
                     "FSD_cm": fsd(J), "ASR": M.asr(J), "join": M.join_jerk(J, joins), "TPE_m": tpe, "TDE_rad": tde,
                     "CCA_steered": top_k(encoders, G[:, s0:], y, 1)})
        if real is not None:
            rows[-1]["FPD"], rows[-1]["Div"] = fpd_div(encoders, X[:, s0:], real)
    return rows


def strides(J: torch.Tensor, height: float = 0.05, speed: float = 0.3) -> list[float]:
    """Stride lengths (m) of world joints J (T, 22, 3): the ground distance between successive
    plants of the same foot joint (a plant: a run of frames with the joint low and slow)."""
    out = []
    for j in M.FEET:
        p = J[:, j]
        v = torch.cat((torch.zeros(1), (p[1:] - p[:-1])[:, [0, 2]].norm(dim=-1) * FPS))
        planted = ((p[:, 1] < height) & (v < speed)).tolist()
        plants, start = [], None
        for t, on in enumerate(planted + [False]):
            if on and start is None:
                start = t
            elif not on and start is not None:
                plants.append(p[start:t, [0, 2]].mean(0))
                start = None
        out += [float((b - a).norm()) for a, b in zip(plants, plants[1:])]
    return out


def stride_by_leg(motor, description: str | None, legs: list[float], n: int = 8, seconds: float = 4.0, speed: float = 1.2,
                  seed: int = 0, cfg: RuntimeConfig | None = None) -> list[dict]:
    """The same description and goal (forward at `speed`) on bodies whose leg_length parameter is
    each of `legs` (others average; description None: no persona, for a plain model): stride length (m, mean over plants after the first second),
    leg length (m, hip to ankle at rest) and foot sliding, per body."""
    from ..body.skeleton import JOINT_INDEX, SHAPE_NAMES, rest_offsets, rest_positions
    from ..runtime.crowd import standing_state
    cfg = cfg or RuntimeConfig()
    rows = []
    for leg in legs:
        shape = torch.zeros(len(SHAPE_NAMES))
        shape[SHAPE_NAMES.index("leg_length")] = leg
        shapes = shape.expand(n, -1).clone()
        init = torch.stack([standing_state(shape) for _ in range(n)])
        setup = None if description is None else (lambda crowd, i, k: crowd.set_persona(i, description))
        goal = torch.tensor([0.0, 0.0, speed]).expand(n, 3)  # the standing bodies face +Z
        X = rollout(motor, init, shapes, int(seconds * FPS), cfg, seed, _controls(setup, goal))
        J = joints_of(X)[:, int(FPS):]
        s = [v for k in range(n) for v in strides(J[k])]
        P = rest_positions(rest_offsets(shape[None], torch.float64))[0]
        leg_m = float((P[JOINT_INDEX["left_hip"]] - P[JOINT_INDEX["left_ankle"]]).norm())
        rows.append({"leg_length": leg, "leg_m": leg_m, "stride_m": sum(s) / max(len(s), 1), "strides": len(s),
                     "FSD_cm": fsd(J)})
    return rows


def recognised(motor, persona: str | None, label: int, encoders: list, init: torch.Tensor, shapes: torch.Tensor,
               seconds: float = 3.0, seed: int = 0, cfg: RuntimeConfig | None = None, speed: float = 1.0,
               settle: float = 0.0) -> dict:
    """The share of rollouts the evaluators read as class `label` (the `seconds` after `settle`):
    avatars given `persona` (a description or a characterized name; None: none), unsteered and
    steered forward at `speed`."""
    cfg = cfg or RuntimeConfig()
    setup = None if persona is None else (lambda crowd, i, k: crowd.set_persona(i, persona))
    s0 = int(settle * FPS)
    out = {}
    for name, goal in (("unsteered", None), ("steered", forward_goals(init, speed))):
        X = rollout(motor, init, shapes, s0 + int(seconds * FPS), cfg, seed, _controls(setup, goal))
        out[name] = top_k(encoders, X[:, s0:], torch.full((len(X),), label), 1)
    return out
