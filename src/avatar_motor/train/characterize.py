"""Few-shot characterization (MotionPersona §6): a persona model fine-tuned on a user's own clip(s)
of about ten seconds, under a unique identifier, so that `set_persona(avatar, NAME)` moves an
avatar like the clip's character under any stick input.

- The clip windows carry the identifier as their text, the body shape estimated from the file's
  own skeleton, and their own trajectory (dropped at `trajectory_dropout`, as in training).
- Prior preservation (Eq. 11's second term): three in four windows of a batch (`clip_share`) are
  the model's own motion under random conditions (training descriptions of the Bandai styles,
  or none for a quarter of the avatars; random bodies, random goals), generated before
  fine-tuning, so the model keeps what it knew without any dataset.
- Initial states from elsewhere (the persona model's own `persona_swap`, stage 2 of its recipe):
  a `swap` share of the clip windows continue from the initial state of the model's own motion
  on the clip's body under other descriptions, one whose ankles and feet are nearest the
  window's. Without it the clip's own first frame already tells its style, the identifier is
  learnt as redundant, and an avatar given the name from another state moved as before.
- The identifier is a fixed random unit vector in the text space (seeded by the name): WordLlama
  pools token embeddings, so a rare-token string (MotionPersona's choice for CLIP) would land near
  ordinary words; a random direction is far from every description the model was trained on.
  With `identifier_lr` it is trained with the weights and saved normalised (textual inversion):
  taught on a youthful walk it moved from the random start (cosine 0.10 with it) to nearest the
  youthful and feminine descriptions, with no label given.
The result is a checkpoint folder (any command's `--model`) whose config maps NAME to that vector.
"""
from __future__ import annotations

import hashlib
import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch

from ..body import rotations as rot
from ..body.motion_state import canonicalize, states_from_motion
from ..body.skeleton import SHAPE_DIM, random_shapes, rest_offsets
from ..model.checkpoint import load_checkpoint, save_checkpoint
from ..model.persona import TEXT_DIM, PersonaCond, trajectory_of
from .losses import motion_loss

NAME_CHARS = set("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_-")


@dataclass
class CharacterizeConfig:
    model: str = "models/primal-bandai-persona"
    clips: list[str] = field(default_factory=list)  # BVH files of the character (about 10 s in all)
    name: str = ""  # the identifier: letters, digits, _ and -
    out: str = ""  # default runs/personas/NAME
    steps: int = 600
    batch: int = 64
    clip_share: float = 0.25  # of the batch: the clip's windows; the rest prior-preservation windows
    lr: float = 5e-5
    trajectory_dropout: float = 0.25
    prior_avatars: int = 32
    prior_seconds: float = 6.0
    fk_weight: float = 20.0
    fkv_weight: float = 0.2
    # a share of the prior avatars move without a description, so that what the model does for an
    # avatar without a persona is preserved too (all with one, it drifted toward the clip's style)
    prior_without_text: float = 0.25
    swap: float = 1.0  # share of the clip windows continued from a feet-matched state of other motion
    swap_neighbours: int = 16  # ... a random one of this many nearest
    # the model's own motion on the clip's body (the swap's other motion, a prior_without_text
    # share of it without a description) joins the prior windows, so that this body without the
    # name keeps moving as before, not only random bodies (measured in the persona card)
    prior_on_clip_body: bool = True
    # Adam's learning rate for the identifier itself (textual inversion: the name's vector moves
    # toward what the model already expresses for such a character; 0: the random vector stays)
    identifier_lr: float = 0.0
    seed: int = 0
    threads: int = 0  # 0 = torch default


def identifier(name: str) -> torch.Tensor:
    g = torch.Generator().manual_seed(int(hashlib.sha256(name.encode()).hexdigest()[:15], 16))
    v = torch.randn(TEXT_DIM, generator=g)
    return v / v.norm()


def clip_windows(paths: list[str], frames: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Canonical windows (W, 1 + frames, 267) of the clips on their own estimated body, and that
    body's shape (SHAPE_DIM,) (the first clip's; a character is one body)."""
    from ..data.retarget import resample, retarget
    from ..io.bvh import BVHError, read_bvh
    wins, shape = [], None
    for p in paths:
        if not Path(p).exists():
            raise FileNotFoundError(f"{p}: no such file")
        try:
            r = resample(retarget(read_bvh(p), body="source"), 30.0)
        except (BVHError, ValueError) as e:
            raise ValueError(f"{p}: not a motion file this project reads ({e})") from None
        s = torch.tensor(r.info["shape"], dtype=torch.float64)
        shape = s if shape is None else shape
        R = rot.quat_to_matrix(torch.from_numpy(r.quats).double())
        X = states_from_motion(torch.from_numpy(r.root_pos).double(), R[:, 0], R[:, 1:], rest_offsets(shape, torch.float64))
        T = len(X)
        if T < frames + 2:
            raise ValueError(f"{p}: {T} frames at 30 fps, fewer than the {frames + 2} one window needs")
        idx = torch.arange(1, T - frames)[:, None] + torch.arange(frames + 1)  # frame 0's velocity is a guess: skip it
        wins.append(canonicalize(X[idx])[0].float())
    return torch.cat(wins), shape.float()


def prior_windows(motor, avatars: int, seconds: float, frames: int, seed: int, shape: torch.Tensor | None = None,
                  without_text: float = 0.0):
    """The model's own motion under random conditions: windows (W, 1 + frames, 267), their shapes,
    texts and whether each had one (a `without_text` share of the avatars is given none). shape
    (SHAPE_DIM,): every avatar on that body instead of random ones."""
    from ..data.personas import DESCRIPTIONS, descriptions
    from ..model.text import embed_texts
    from ..runtime.crowd import Crowd, RuntimeConfig
    g = torch.Generator().manual_seed(seed)
    texts = [d for lab in sorted(DESCRIPTIONS) for d in descriptions(lab)]
    pick = torch.randint(len(texts), (avatars,), generator=g).tolist()
    has_text = torch.rand(avatars, generator=g) >= without_text
    shapes = random_shapes(avatars, g) if shape is None else shape.float().expand(avatars, SHAPE_DIM).clone()
    crowd = Crowd(motor, RuntimeConfig(), seed)
    ids = [crowd.spawn(shape=shapes[k], position=(3.0 * k, 0.0)) for k in range(avatars)]
    for k, i in enumerate(ids):
        if has_text[k]:
            crowd.set_persona(i, texts[pick[k]])
    made = {i: [crowd.state(i)[None]] for i in ids}
    seg = 0
    while sum(len(s) for s in made[ids[0]]) < seconds * 30:
        if seg % 4 == 0:  # a new goal every 2 s: some stand, most walk or run somewhere
            for i in ids:
                speed = float(torch.rand(1, generator=g)) * 2.5
                a = float(torch.rand(1, generator=g)) * 6.2832
                crowd.set_goal(i, None if speed < 0.4 else (speed * float(torch.cos(torch.tensor(a))),
                                                            speed * float(torch.sin(torch.tensor(a)))))
        out = crowd.step_segment()
        for i in ids:
            made[i].append(out[i])
        seg += 1
    X = torch.stack([torch.cat(made[i]) for i in ids]).double()  # (A, T, 267)
    T = X.shape[1]
    idx = torch.arange(0, T - frames - 1, 5)[:, None] + torch.arange(frames + 1)
    W = canonicalize(X[:, idx].flatten(0, 1))[0].float()
    n = len(idx)
    emb = embed_texts(texts)[torch.tensor(pick)] * has_text[:, None]
    return W, shapes.repeat_interleave(n, 0), emb.repeat_interleave(n, 0), has_text.repeat_interleave(n, 0)


def swap_partners(clip: torch.Tensor, starts: torch.Tensor, norm, k: int) -> torch.Tensor:
    """For each clip window (W, 1 + N, 267), the indices (W, k) of the k windows of `starts` whose
    initial states' ankles and feet (positions and velocities, normalised) are nearest."""
    from .adapt import _match_features
    f = _match_features("feet")
    d = torch.cdist(norm.encode(clip[:, 0])[:, f], norm.encode(starts[:, 0])[:, f])
    return d.topk(min(k, len(starts)), largest=False).indices


def characterize(cfg: CharacterizeConfig, progress=print) -> Path:
    if not cfg.name or set(cfg.name) - NAME_CHARS or len(cfg.name) > 40:
        raise ValueError(f"--name {cfg.name!r}: use 1-40 letters, digits, _ or - (the identifier avatars are given)")
    if not cfg.clips:
        raise ValueError("give the character's clip(s): avatar-motor adapt persona CLIP.bvh [...] --name NAME")
    for share in ("swap", "prior_without_text"):
        if not 0.0 <= getattr(cfg, share) <= 1.0:
            raise ValueError(f"{share} is a share: give a value in [0, 1], not {getattr(cfg, share)}")
    if not 0.0 < cfg.clip_share < 1.0:
        raise ValueError(f"clip_share is a share of the batch: give a value between 0 and 1, not {cfg.clip_share}")
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    motor = load_checkpoint(cfg.model)
    if not motor.net.cfg.persona:
        raise ValueError(f"{cfg.model} has no persona conditions: characterize a persona model (configs/persona.json)")
    N = motor.net.cfg.frames
    out = Path(cfg.out or f"runs/personas/{cfg.name}")
    t0 = time.time()
    clip, shape = clip_windows(cfg.clips, N)
    progress(f"{len(cfg.clips)} clip(s): {len(clip)} windows ({(len(clip) + N) / 30:.1f} s) on a body of shape "
             f"{[round(v, 2) for v in shape.tolist()]}")
    prior, p_shapes, p_text, p_has_text = prior_windows(motor, cfg.prior_avatars, cfg.prior_seconds, N, cfg.seed,
                                                        without_text=cfg.prior_without_text)
    progress(f"prior preservation: {len(prior)} windows of the model's own motion ({time.time() - t0:.0f} s)")
    if cfg.swap > 0 or cfg.prior_on_clip_body:
        starts, s_shapes, s_text, s_has_text = prior_windows(
            motor, cfg.prior_avatars, cfg.prior_seconds, N, cfg.seed + 1, shape,
            without_text=cfg.prior_without_text if cfg.prior_on_clip_body else 0.0)
        progress(f"other motion: {len(starts)} windows on the clip's body ({time.time() - t0:.0f} s)")
    if cfg.swap > 0:
        partners = swap_partners(clip, starts, motor.norm, cfg.swap_neighbours)
    if cfg.prior_on_clip_body:
        prior, p_shapes = torch.cat((prior, starts)), torch.cat((p_shapes, s_shapes))
        p_text, p_has_text = torch.cat((p_text, s_text)), torch.cat((p_has_text, s_has_text))
    ident = identifier(cfg.name)
    net, norm, diffusion = motor.net, motor.norm, motor.diffusion
    net.train()
    ident = torch.nn.Parameter(ident.clone(), requires_grad=cfg.identifier_lr > 0)
    groups = [{"params": list(net.parameters()), "lr": cfg.lr}]
    if cfg.identifier_lr > 0:
        groups.append({"params": [ident], "lr": cfg.identifier_lr, "weight_decay": 0.0})
    opt = torch.optim.AdamW(groups, lr=cfg.lr)
    g = torch.Generator().manual_seed(cfg.seed)
    n_clip = max(1, min(cfg.batch - 1, round(cfg.batch * cfg.clip_share)))  # the clip's windows per batch
    for step in range(cfg.steps):
        ci = torch.randint(len(clip), (n_clip,), generator=g)
        pi = torch.randint(len(prior), (cfg.batch - n_clip,), generator=g)
        x = torch.cat((clip[ci], prior[pi]))
        shapes = torch.cat((shape.expand(n_clip, SHAPE_DIM), p_shapes[pi]))
        text = torch.cat(((ident / ident.norm()).expand(n_clip, TEXT_DIM), p_text[pi]))
        present = torch.ones(cfg.batch, 3, dtype=torch.bool)
        present[n_clip:, 0] = p_has_text[pi]
        present[:, 2] = torch.rand(cfg.batch, generator=g) >= cfg.trajectory_dropout
        cond = PersonaCond(text, shapes, trajectory_of(x[:, 1:]), present)
        xn = norm.encode(x)
        x_init = x[:, 0]  # the state the network continues from: the window's own, or (swap) another's
        if cfg.swap > 0:
            rows = (torch.rand(n_clip, generator=g) < cfg.swap).nonzero()[:, 0]
            pick = partners[ci[rows], torch.randint(partners.shape[1], (len(rows),), generator=g)]
            x_init = x_init.clone()
            x_init[rows] = starts[pick, 0]
        t = torch.randint(diffusion.T, (cfg.batch,), generator=g)
        x_t = diffusion.q_sample(xn[:, 1:], t, torch.randn(xn[:, 1:].shape, generator=g))
        losses = motion_loss(net(t, x_t, norm.encode(x_init), None, cond), xn[:, 1:], x[:, 0], shapes, norm,
                             cfg.fk_weight, cfg.fkv_weight)
        opt.zero_grad(set_to_none=True)
        losses["loss"].backward()
        opt.step()
        if (step + 1) % 50 == 0 or step + 1 == cfg.steps:
            progress(f"step {step + 1}/{cfg.steps}: loss {float(losses['loss'].detach()):.4f} ({time.time() - t0:.0f} s)")
    net.eval()
    ident = (ident / ident.norm()).detach()
    personas = {**motor.config.get("personas", {}), cfg.name: [float(v) for v in ident]}
    extra = {k: v for k, v in motor.config.items() if k in ("name", "licence", "trained_steps", "training_data", "train_config")}
    extra.update(name=f"{motor.name}+{cfg.name}", personas=personas,
                 characterized={"name": cfg.name, "clips": [Path(c).name for c in cfg.clips], "shape": shape.tolist(),
                                "from": str(cfg.model), "config": asdict(cfg)})
    card = (f"# {cfg.name}: {motor.name} characterized (non-commercial)\n\n{motor.name} fine-tuned for "
            f"{cfg.steps} steps on {len(cfg.clips)} clip(s) ({(len(clip) + N) / 30:.1f} s) with prior preservation, "
            f"in {time.time() - t0:.0f} s. Give an avatar the persona `{cfg.name}` to move it as the clip's character. "
            "The base weights were trained on CC BY-NC 4.0 data: non-commercial use only.\n\n"
            f"```\n{json.dumps(asdict(cfg), indent=1)}\n```\n")
    save_checkpoint(out, net, norm, extra, card)
    progress(f"{out}: the persona {cfg.name!r} ({time.time() - t0:.0f} s in all)")
    return out
