"""Adaptation training (PRIMAL §4, supplementary §9.3): a frozen base model plus an adaptor for
action labels (few-shot) or 2-D targets, trained with the same losses as the base and control
dropout for classifier-free guidance."""
from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

from ..body.skeleton import ANKLES_AND_FEET, NUM_JOINTS, SHAPE_DIM
from ..data.cache import MotionCache
from ..data.dataset import SegmentConfig, SegmentDataset
from ..body.motion_state import SLICES
from ..model.adaptor import AdaptedDenoiser, AdaptorConfig, base_fingerprint, save_adaptor
from ..model.checkpoint import load_checkpoint
from .losses import motion_loss
from ..io.atomic import recover_folder, replace_folder
from .trainer import EMA, _flatten_optimizer, _state_complete, _unflatten_optimizer, resolve_caches


@dataclass
class AdaptConfig:
    base: str = "models/primal-bandai"
    data: list[str] = field(default_factory=lambda: ["dataset-1"])
    out: str = "runs/adapt"
    task: str = "actions"  # or "reach"
    kind: str = "controlnet"  # or "omni", "finetune"
    label_key: str = "content"  # which clip label names the action
    classes: list[str] = field(default_factory=list)  # empty: every label value found
    clips_per_class: int = 0  # few-shot: keep the first N clips (by file name) of each class; 0 = all
    steps: int = 2000
    batch: int = 16  # PRIMAL: 16 for actions, 128 for reaching
    lr: float = 1e-4
    control_dropout: float = 0.1
    fk_weight: float = 20.0
    fkv_weight: float = 0.2
    seed: int = 0
    split: str = "train"
    scratch: bool = False  # PRIMAL's "scratch training" baseline: a fresh network, trained like finetune
    # our addition: the fraction of windows whose initial state is swapped for one from another
    # window (for actions: of another class; same body shape); 0 is PRIMAL's recipe. In few-shot
    # clips the initial state already tells the action, so without this the label is nearly
    # redundant and the adaptor ignores it from any other state (measured, 5 Bandai classes, 30 min:
    # R-precision 0.227 with 0, 0.920 with 0.5, 45 held-out states x 5 labels). On cache version 3,
    # one core: 0.867 at 0.5, 0.916 / 0.907 (two seeds) at 0.8, 0.960 at 1.0 but skating (ASR 0.138
    # vs 0.06: no labelled window then continues its own state); with the states matched by the feet
    # (swap_match) every window swapped reads 0.920-0.960 (six runs, two at 0.96, mean 0.939) at ASR
    # 0.058-0.072: the README's few-shot recipe
    swap_initial: float = 0.5
    # our addition: 0 swaps in the initial state of any window; K > 0 the state of one of the K
    # windows (of other clips) whose initial states are nearest to the window's own (canonical joint
    # positions and velocities), so the swapped state nearly continues into the window's motion.
    # Measured (eval reach, 30 min): K = 0 (any, constant rate) 0.048 m / ASR 0.081; cosine rate:
    # 128 0.035 / 0.069, 512 0.031 / 0.068. Its rollouts' raw seams are not smoother (acceleration
    # across a seam without inertialization 81 m/s^2 vs 60 for K = 0): why it helps is not measured
    swap_neighbours: int = 0
    # our addition: what "nearest" compares for --swap-neighbours: "state" (all joint positions and
    # velocities) or "feet" (ankle and foot positions and velocities only): the swapped-in state then
    # stands where the window's own feet are, so learning to turn it into the action moves no
    # planted foot, while its upper body can be anything (measured above, with swap_initial 1 and K = 2048;
    # K = 512 0.876, 8192 0.889, one seed each)
    swap_match: str = "state"
    swap_pool: int = 30000  # windows searched for neighbours (a random subset of a large dataset)
    # our addition: motion caches whose (training-split) windows supply the swapped-in initial
    # states, none of them of the commanded label; empty: the adaptation data itself. Only their
    # first frames are used (no labels, nothing of their motion is learnt): the few-shot set
    # stays the labelled motion, and the states are the kind an avatar is in when a label comes
    # (the base model's own data: walking, running, anything)
    swap_data: list[str] = field(default_factory=list)
    max_minutes: float = 0.0  # stop early after this much wall time (0 = run all steps)
    # the saved adaptor is an exponential moving average of the trained weights (0 = the last
    # weights), as the base model's training does: at batch 16 and lr 3e-4 the last weights
    # wander, and two runs of one recipe ended at R-precision 0.92 and 0.63 without it
    ema_decay: float = 0.999
    ema_start: int = 1000  # steps before the average starts tracking
    # "cosine": the learning rate falls from lr to 0 over the run (over max_minutes of wall time
    # when that limit is set, as a time-limited run does not know its step count); "constant": lr throughout
    lr_schedule: str = "constant"
    # left/right mirroring of the training windows; None: off for actions, on for reaching. A
    # person's action has a handedness that is part of it (every Bandai guide points with the
    # right hand; with mirrored windows 21 of 45 guide rollouts used the left); a target has none.
    # Measured (5 classes, 30 min): R-precision 0.844 without, 0.787 with (guide read 31 vs 13 of 45)
    mirror: bool | None = None
    # the training state (weights, average, optimizer, random streams, step, elapsed time) is
    # saved every this many steps, and a run started again with the same `out` continues from it
    checkpoint_every: int = 250
    threads: int = 0  # 0 = torch default


def target_of(x: torch.Tensor) -> torch.Tensor:
    """The reaching target of a canonical window: pelvis XZ of its last frame."""
    J = x[:, -1, SLICES["joints"]].reshape(-1, 22, 3)
    return J[:, 0, [0, 2]]


def _progress(step: int, cfg: AdaptConfig, seconds: float) -> float:
    """How far through its run a training is, in [0, 1]: by steps, or by wall time when limited."""
    done = step / max(1, cfg.steps)
    if cfg.max_minutes:
        done = max(done, seconds / (cfg.max_minutes * 60))
    return min(1.0, done)


def _match_features(match: str) -> torch.Tensor:
    """Indices into a motion state of what swap_match compares: all joints' positions and
    velocities, or only those of the ankles and feet."""
    joints = range(NUM_JOINTS) if match == "state" else ANKLES_AND_FEET
    return torch.tensor([s.start + 3 * j + k for s in (SLICES["joints"], SLICES["velocities"]) for j in joints for k in range(3)])


class _NeighbourPool:
    """Initial-state features of a random subset of the dataset's windows (each with its mirroring
    fixed), for finding a window whose initial state resembles a given one."""

    def __init__(self, ds: SegmentDataset, norm, n: int, gen: torch.Generator, match: str = "state"):
        self.feature_index = _match_features(match)
        self.index = torch.randperm(len(ds.window_starts), generator=gen)[:n]
        self.mirror = torch.rand(len(self.index), generator=gen) < 0.5 if ds.cfg.mirror else torch.zeros(len(self.index), dtype=torch.bool)
        feats = []
        for idx, mir in zip(self.index.split(2048), self.mirror.split(2048)):
            x, _ = ds.windows(ds.window_starts[idx], gen, shapes=torch.zeros(len(idx), SHAPE_DIM), mirror=mir)
            feats.append(self.features(norm.encode(x[:, 0])))
        self.feats = torch.cat(feats)
        self.clip = ds.window_clip[self.index]

    def features(self, x0n: torch.Tensor) -> torch.Tensor:
        return x0n[:, self.feature_index]

    def partners(self, x0n: torch.Tensor, clips: torch.Tensor, k: int, gen: torch.Generator,
                 allowed: torch.Tensor | None = None) -> torch.Tensor:
        """For each normalised initial state, a random one of its k nearest pool entries of another
        clip (and, if given, where allowed (B, pool) is true). Returns pool positions."""
        d = torch.cdist(self.features(x0n), self.feats)
        banned = self.clip[None] == clips[:, None]
        if allowed is not None:
            banned |= ~allowed
        d[banned] = float("inf")
        near = d.topk(min(k, d.shape[1]), largest=False).indices
        return near[torch.arange(len(near)), torch.randint(near.shape[1], (len(near),), generator=gen)]


# what a continued run may change: how long it runs, how it checkpoints, where its folder is
_MAY_CHANGE = ("steps", "max_minutes", "checkpoint_every", "threads", "out")


def _recipe(cfg: AdaptConfig) -> dict:
    return {k: v for k, v in asdict(cfg).items() if k not in _MAY_CHANGE}


def _save_state(folder: Path, cfg: AdaptConfig, step: int, seconds: float, trainable: dict, ema: EMA, opt,
                gen: torch.Generator, log: list[float]) -> None:
    """An adaptation's training state, swapped in whole (io/atomic.py): a kill at any instant
    leaves the previous state or this one."""
    opt_t, opt_meta = _flatten_optimizer(opt)
    tensors = {**{f"net.{k}": v.detach() for k, v in trainable.items()}, **{f"ema.{k}": v for k, v in ema.shadow.items()},
               **opt_t, "rng.data": gen.get_state(), "rng.torch": torch.get_rng_state(),
               "loss": torch.tensor(log, dtype=torch.float64)}

    def fill(tmp: Path) -> None:
        save_file({k: v.contiguous() for k, v in tensors.items()}, str(tmp / "state.safetensors"))
        # written last: marks the state complete
        (tmp / "state.json").write_text(json.dumps({"step": step, "seconds": seconds, "recipe": _recipe(cfg), "optimizer": opt_meta}))

    replace_folder(folder, fill, _state_complete)


def _resume(folder: Path, cfg: AdaptConfig, trainable: dict, ema: EMA, opt, gen: torch.Generator,
            log: list[float]) -> tuple[int, float]:
    """Load a saved adaptation state into the run (weights, average, optimizer, random streams,
    the loss log); returns (step, seconds trained), (0, 0) for a new run."""
    st = recover_folder(folder, _state_complete)
    if st is None:
        return 0, 0.0
    meta = json.loads((st / "state.json").read_text())
    recipe = _recipe(cfg)
    changed = sorted(k for k in recipe if meta.get("recipe", {}).get(k) != recipe[k])  # (a train run has none)
    if changed:
        raise ValueError(f"{folder} holds the state of another adaptor run (its {', '.join(changed)} differ from this "
                         "config's; a continued run may change only " + ", ".join(_MAY_CHANGE) + "): give this run "
                         "another out folder, or delete that one to start afresh")
    tensors = load_file(str(st / "state.safetensors"))
    with torch.no_grad():
        for k, p in trainable.items():
            p.copy_(tensors[f"net.{k}"])
    ema.shadow = {k: tensors[f"ema.{k}"].clone() for k in trainable}
    opt.load_state_dict(_unflatten_optimizer(tensors, meta["optimizer"]))
    gen.set_state(tensors["rng.data"])
    torch.set_rng_state(tensors["rng.torch"])
    log.extend(tensors["loss"].tolist())
    return meta["step"], meta["seconds"]


def _label_filter(caches: list[MotionCache], cfg: AdaptConfig, classes: list[str]):
    """Which clips form the adaptation set: those labelled with one of `classes`, at most
    cfg.clips_per_class of each (the first by file name among the chosen split)."""
    from ..data.cache import is_held_out
    wanted = {"train": False, "heldout": True}.get(cfg.split)
    chosen: dict[str, list[str]] = {c: [] for c in classes}
    for clip in sorted((c for m in caches for c in m.clips), key=lambda c: c["key"]):
        label = clip["labels"].get(cfg.label_key)
        if label in chosen and (wanted is None or is_held_out(clip["key"]) == wanted):
            chosen[label].append(clip["key"])
    if cfg.clips_per_class > 0:
        chosen = {c: keys[: cfg.clips_per_class] for c, keys in chosen.items()}
    keys = {k for ks in chosen.values() for k in ks}
    return lambda clip: clip["key"] in keys


def adapt(cfg: AdaptConfig, progress: bool = True) -> Path:
    from tqdm import tqdm

    if cfg.task not in ("actions", "reach"):
        raise ValueError(f"task must be 'actions' or 'reach', got {cfg.task!r}")
    if not 0.0 <= cfg.ema_decay < 1.0:
        raise ValueError(f"ema_decay must be in [0, 1), not {cfg.ema_decay}")
    if not 0.0 <= cfg.swap_initial <= 1.0:
        raise ValueError(f"swap_initial is a fraction of the training windows: give a value in [0, 1], not {cfg.swap_initial}")
    if cfg.swap_neighbours < 0:
        raise ValueError(f"swap_neighbours is a count of windows (0 = any window), not {cfg.swap_neighbours}")
    if cfg.swap_match not in ("state", "feet"):
        raise ValueError(f"swap_match must be 'state' or 'feet', not {cfg.swap_match!r}")
    if cfg.swap_match != "state" and cfg.swap_neighbours == 0:
        raise ValueError("swap_match chooses what swap_neighbours compares: give swap_neighbours K too")
    if cfg.swap_data:
        if cfg.swap_initial == 0:
            raise ValueError("swap_data supplies the swapped-in initial states: use it with swap_initial above 0")
        resolve_caches(cfg.swap_data)  # a missing cache is named before anything loads
    if cfg.lr_schedule not in ("constant", "cosine"):
        raise ValueError(f"lr_schedule must be 'constant' or 'cosine', not {cfg.lr_schedule!r}")
    if cfg.checkpoint_every < 1:
        raise ValueError(f"checkpoint_every is a number of steps (1 or more), not {cfg.checkpoint_every}")
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    motor = load_checkpoint(cfg.base)
    shipped_net = motor.net  # the base the adaptor is used with (and recorded against)
    if cfg.scratch:
        if cfg.kind != "finetune":
            raise ValueError("scratch trains the whole network: use it with kind finetune")
        from ..model.denoiser import Denoiser
        motor.net = Denoiser(motor.net.cfg)  # same architecture and normalisation, fresh weights
    caches = [MotionCache.load(p) for p in resolve_caches(cfg.data)]
    keep = None
    if cfg.task == "actions":
        found = sorted({c["labels"].get(cfg.label_key) for m in caches for c in m.clips} - {None})
        classes = cfg.classes or found
        unknown = sorted(set(classes) - set(found))
        if unknown or not classes:
            raise ValueError(f"labels {unknown or classes} are not among the '{cfg.label_key}' labels of the data: {found}")
        keep = _label_filter(caches, cfg, classes)
    else:
        classes = []
    mirrored = cfg.task == "reach" if cfg.mirror is None else cfg.mirror
    ds = SegmentDataset(caches, SegmentConfig(split=cfg.split, mirror=mirrored), clip_filter=keep)
    acfg = AdaptorConfig(kind=cfg.kind, control="label" if cfg.task == "actions" else "target", labels=list(classes),
                         control_dropout=cfg.control_dropout)
    model = AdaptedDenoiser(motor.net, acfg)
    model.base_fingerprint = base_fingerprint(shipped_net)  # for --scratch too: it runs beside this base
    model.train()
    trainable = {n: p for n, p in model.named_parameters() if p.requires_grad}
    opt = torch.optim.AdamW(list(trainable.values()), lr=cfg.lr)
    ema = EMA(trainable, cfg.ema_decay)
    gen = torch.Generator().manual_seed(cfg.seed)
    label_index = {c: k for k, c in enumerate(classes)}

    def clip_classes(d: SegmentDataset) -> torch.Tensor:
        """Each clip's class index (-1: none of ours), looked up once, not per training step."""
        return torch.tensor([label_index.get(lb.get(cfg.label_key), -1) for lb in d.clip_labels])
    ds_label = clip_classes(ds)
    t0 = time.time()  # the neighbour search's set-up counts against --max-minutes too
    # where swapped-in initial states come from, and the class of each of its clips
    states, states_label = ds, ds_label
    if cfg.swap_data:  # (validated above: only with --swap-initial above 0)
        states = SegmentDataset([MotionCache.load(p) for p in resolve_caches(cfg.swap_data)],
                                SegmentConfig(split=cfg.split, mirror=mirrored))
        states_label = clip_classes(states)
    pool = _NeighbourPool(states, motor.norm, cfg.swap_pool, gen, cfg.swap_match) if cfg.swap_initial > 0 and cfg.swap_neighbours > 0 else None
    pool_labels = states_label[pool.clip] if pool is not None else None
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    state_dir = out / "train_state"
    log: list[float] = []
    first, seconds = _resume(state_dir, cfg, trainable, ema, opt, gen, log)
    if first:
        t0 -= seconds  # a wall-time limit (and the info's seconds) count the time already trained
        print(f"resumed from {state_dir} at step {first}", flush=True)
    (out / "adapt_config.json").write_text(json.dumps(asdict(cfg), indent=1))
    bar = tqdm(range(first, cfg.steps), desc=f"adapt {cfg.task} ({cfg.kind})", disable=not progress, mininterval=5,
               initial=first, total=cfg.steps)
    for step in bar:
        if cfg.max_minutes and time.time() - t0 > cfg.max_minutes * 60:
            break
        if cfg.lr_schedule == "cosine":
            for group in opt.param_groups:
                group["lr"] = cfg.lr * 0.5 * (1 + math.cos(math.pi * _progress(step, cfg, time.time() - t0)))
        x, shapes, clip = ds.sample_indexed(cfg.batch, gen)
        if cfg.task == "actions":
            y = ds_label[clip]
        else:
            y = target_of(x)
        xn = motor.norm.encode(x)
        x0n = xn[:, 0]
        drop = torch.rand(cfg.batch, generator=gen) < cfg.control_dropout
        if cfg.swap_initial > 0:
            if pool is None:
                other = torch.randint(len(states.window_starts), (cfg.batch,), generator=gen)
            swap = (torch.rand(cfg.batch, generator=gen) < cfg.swap_initial) & ~drop  # the null control keeps its state
            # actions: only a state of another class (a state of the commanded action is continued)
            if pool is None and cfg.task == "actions":
                swap &= states_label[states.window_clip[other]] != y
            rows = swap.nonzero()[:, 0]
            if len(rows):  # build only the swapped windows: this is the training loop's hot path
                if pool is None:
                    starts, mirror = states.window_starts[other[rows]], None
                else:
                    allowed = pool_labels[None] != y[rows][:, None] if cfg.task == "actions" else None
                    # a window of the same clip is never a partner (clip numbers are the adaptation set's)
                    own = clip[rows] if states is ds else torch.full((len(rows),), -1)
                    pick = pool.partners(x0n[rows], own, cfg.swap_neighbours, gen, allowed)
                    starts, mirror = states.window_starts[pool.index[pick]], pool.mirror[pick]
                xo, _ = states.windows(starts, gen, shapes=shapes[rows], mirror=mirror)
                x0n = x0n.clone()
                x0n[rows] = motor.norm.encode(xo[:, 0])
        t = torch.randint(motor.diffusion.T, (cfg.batch,), generator=gen)
        noise = torch.randn(xn[:, 1:].shape, generator=gen)
        x_t = motor.diffusion.q_sample(xn[:, 1:], t, noise)
        pred = model(t, x_t, x0n, y, drop=drop)
        losses = motion_loss(pred, xn[:, 1:], x[:, 0], shapes, motor.norm, cfg.fk_weight, cfg.fkv_weight)
        opt.zero_grad(set_to_none=True)
        losses["loss"].backward()
        opt.step()
        ema.update(trainable, active=step >= cfg.ema_start)
        log.append(float(losses["loss"].detach()))
        if (step + 1) % 25 == 0:
            bar.set_postfix(loss=f"{sum(log[-25:]) / 25:.4f}")
        if (step + 1) % cfg.checkpoint_every == 0:
            _save_state(state_dir, cfg, step + 1, time.time() - t0, trainable, ema, opt, gen, log)
    if len(log) % cfg.checkpoint_every:  # where the run ended (steps or wall time): it can be continued
        _save_state(state_dir, cfg, len(log), time.time() - t0, trainable, ema, opt, gen, log)
    info = {"task": cfg.task, "steps": len(log), "batch": cfg.batch, "kind": cfg.kind, "scratch": cfg.scratch, "seconds": time.time() - t0, "windows": len(ds),
            "frames": ds.frames_total, "minutes_of_data": ds.frames_total / 30 / 60, "final_loss": sum(log[-50:]) / max(1, len(log[-50:])), "ema_decay": cfg.ema_decay, "lr_schedule": cfg.lr_schedule, "swap_initial": cfg.swap_initial, "swap_neighbours": cfg.swap_neighbours, "swap_match": cfg.swap_match, "swap_data": cfg.swap_data, "mirror": mirrored,
            "licence": motor.config.get("licence", "")}
    with torch.no_grad():
        for n, p in trainable.items():
            p.copy_(ema.shadow[n])
    model.eval()
    return save_adaptor(out / "adaptor", model, motor.name, info)
