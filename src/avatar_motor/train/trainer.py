"""Training loop: AdamW, EMA, checkpoints with exact resume, progress with steps/s and ETA, a
metrics log and a loss-curve PNG, and data-parallel training through torchrun (gloo on CPU).

Exact resume: the data/noise generator, torch's global RNG (dropout), the optimizer, the EMA and
the step are saved (safetensors + JSON, no pickle). Data parallelism: every rank draws the same
global batch and trains on its own slice, so N processes with batch B/N each reproduce one
process with batch B.
"""
from __future__ import annotations

import atexit
import json
import math
import os
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import torch
import torch.distributed as dist
from safetensors.torch import load_file, save_file

from ..data.cache import MotionCache, default_cache_dir
from .. import config
from ..data.dataset import SegmentConfig, SegmentDataset, load_or_compute_stats
from ..io.atomic import recover_folder, replace_folder, write_file
from ..model.checkpoint import checkpoint_complete, load_checkpoint, save_checkpoint
from ..model.denoiser import Denoiser, DenoiserConfig
from ..model.diffusion import Diffusion
from ..model.persona import CONDITIONS, TEXT_DIM, PersonaCond, trajectory_of
from .losses import motion_loss

LICENCE_NOTE = ("Trained on the Bandai Namco Research Motion Dataset (CC BY-NC 4.0): the weights are for "
                "non-commercial use only.")


@dataclass
class TrainConfig:
    data: list[str] = field(default_factory=lambda: ["dataset-1", "dataset-2"])  # cache names or .npz paths
    out: str = "runs/base"
    steps: int = 6000
    batch: int = 256
    lr: float = 1e-4
    warmup: int = 0  # linear warm-up steps
    lr_final_ratio: float = 1.0  # cosine decay to lr * ratio at `steps` (1.0 = constant, as PRIMAL)
    stop_at: int = 0  # end the run at this step, its schedule still planned for `steps` (0: at `steps`)
    weight_decay: float = 0.0
    ema_decay: float = 0.999
    ema_start: int = 500  # steps before the EMA starts tracking (PRIMAL starts after 5 % of training)
    fk_weight: float = 20.0  # per m^2 of joint-position error
    fkv_weight: float = 0.2  # per (m/s)^2 of joint-velocity error
    checkpoint_every: int = 250
    log_every: int = 25
    seed: int = 0
    threads: int = 0  # 0 = torch default
    diffusion_steps: int = 50
    init: str = ""  # warm start: a checkpoint folder whose weights (same model config) start the run
    # with init: keep its normalisation (continuing a model on added data) instead of computing
    # the data's (following re-imported data)
    init_stats: bool = False
    # persona networks (model.persona): the chance that each condition (text, shape, trajectory)
    # is left out of a training window, so that every one may be absent at run time
    persona_dropout: float = 0.25
    # persona networks: the share of windows with a text whose initial state (what the network
    # continues from) is swapped for that of a window of another style, one of the
    # persona_neighbours whose ankles and feet are nearest (train/adapt.py's swap, for the same
    # reason: the initial state already tells the style, so without it the text is redundant)
    persona_swap: float = 0.0
    persona_neighbours: int = 256
    # persona networks: conditions never given in training (ablations, MotionPersona Table 5):
    # any of "text", "shape", "trajectory"
    persona_without: list[str] = field(default_factory=list)
    model: DenoiserConfig = field(default_factory=DenoiserConfig)
    segment: SegmentConfig = field(default_factory=SegmentConfig)
    name: str = "avatar-motor-base"
    licence: str = LICENCE_NOTE

    @staticmethod
    def from_dict(d: dict) -> "TrainConfig":
        return config.from_dict(TrainConfig, d, "training config")


class PersonaTexts:
    """The training descriptions of each clip's style label (data/personas.py), embedded once."""

    def __init__(self, ds: SegmentDataset):
        from ..data.personas import DESCRIPTIONS, descriptions
        from ..model.text import embed_texts
        labels = sorted({lab.get("style") for lab in ds.clip_labels if lab.get("style") in DESCRIPTIONS})
        self.sentences = [descriptions(lab) for lab in labels]
        n = max((len(s) for s in self.sentences), default=1)
        self.table = torch.zeros(len(labels) + 1, n, TEXT_DIM)  # the last row: no style
        for i, ss in enumerate(self.sentences):
            e = embed_texts(ss)
            self.table[i] = e[torch.arange(n) % len(ss)]  # a label with fewer sentences repeats them
        index = {lab: i for i, lab in enumerate(labels)}
        self.clip_style = torch.tensor([index.get(lab.get("style"), len(labels)) for lab in ds.clip_labels])
        self.none = len(labels)

    def draw(self, clip: torch.Tensor, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        style = self.clip_style[clip]
        pick = torch.randint(self.table.shape[1], (len(clip),), generator=gen)
        return self.table[style, pick], style != self.none


def resolve_caches(names: list[str]) -> list[Path]:
    out = []
    for n in names:
        p = Path(n)
        if p.suffix != ".npz":
            p = default_cache_dir() / f"{n}.npz"
        if not p.exists():
            raise FileNotFoundError(f"motion cache {p} not found; run 'avatar-motor data import PATH' first")
        out.append(p)
    return out


class EMA:
    """Moving average of named tensors: a network's state_dict, or an adaptor's trainable
    parameters (train/adapt.py). Until `active`, the average is a copy."""

    def __init__(self, tensors: dict[str, torch.Tensor], decay: float):
        self.decay = decay
        self.shadow = {k: v.detach().clone() for k, v in tensors.items()}

    @torch.no_grad()
    def update(self, tensors: dict[str, torch.Tensor], active: bool) -> None:
        for k, v in tensors.items():
            if active and v.dtype.is_floating_point:
                self.shadow[k].mul_(self.decay).add_(v.detach(), alpha=1 - self.decay)
            else:
                self.shadow[k].copy_(v)


def _flatten_optimizer(opt: torch.optim.Optimizer) -> tuple[dict[str, torch.Tensor], dict]:
    sd = opt.state_dict()
    tensors, meta = {}, {"param_groups": sd["param_groups"], "state_keys": {}}
    for pid, st in sd["state"].items():
        meta["state_keys"][str(pid)] = list(st)
        for k, v in st.items():
            tensors[f"opt.{pid}.{k}"] = v if torch.is_tensor(v) else torch.tensor(v)
    return tensors, meta


def _unflatten_optimizer(tensors: dict, meta: dict) -> dict:
    state = {int(pid): {k: tensors[f"opt.{pid}.{k}"] for k in keys} for pid, keys in meta["state_keys"].items()}
    return {"state": state, "param_groups": meta["param_groups"]}


class Trainer:
    def __init__(self, cfg: TrainConfig, progress: bool = True):
        self.cfg = cfg
        self.progress = progress
        self.rank, self.world = 0, 1
        if int(os.environ.get("WORLD_SIZE", "1")) > 1:
            if not dist.is_initialized():
                dist.init_process_group("gloo")
                # a process leaving with its gloo group alive can abort in the group's destructor
                # ("terminate called without an active exception") while the other rank still saves
                atexit.register(dist.destroy_process_group)
            self.rank, self.world = dist.get_rank(), dist.get_world_size()
            if cfg.batch % self.world:
                raise ValueError(f"batch {cfg.batch} must divide by the {self.world} processes")
        if cfg.threads:
            torch.set_num_threads(cfg.threads)
        self.out = Path(cfg.out)
        self.state_dir = self.out / "train_state"  # what resuming reads
        self.cache_paths = resolve_caches(cfg.data)
        caches = [MotionCache.load(p) for p in self.cache_paths]
        self.ds = SegmentDataset(caches, cfg.segment)
        if cfg.model.persona:
            self.texts = PersonaTexts(self.ds)
        unknown = set(cfg.persona_without) - set(CONDITIONS)
        if unknown:
            raise ValueError(f"persona_without names conditions {sorted(unknown)}; the conditions are {list(CONDITIONS)}")
        if not 0.0 <= cfg.persona_swap <= 1.0:
            raise ValueError(f"persona_swap is a share of the windows: give a value in [0, 1], not {cfg.persona_swap}")
        if cfg.init_stats and not cfg.init:
            raise ValueError("init_stats keeps the init checkpoint's normalisation; set init to that checkpoint")
        self.norm = load_checkpoint(cfg.init).norm if cfg.init_stats else load_or_compute_stats(self.ds, self.cache_paths)
        torch.manual_seed(cfg.seed)
        self.net = Denoiser(cfg.model)
        if cfg.init and not (self.state_dir / "state.json").exists():  # a resumed run has its own weights
            self._warm_start(cfg.init)
        self.pool = None
        if cfg.model.persona and cfg.persona_swap > 0:
            from .adapt import _NeighbourPool  # (adapt imports this module)
            self.pool = _NeighbourPool(self.ds, self.norm, 30000, torch.Generator().manual_seed(cfg.seed + 1), "feet")
            self.pool_style = self.texts.clip_style[self.pool.clip]
        self.diffusion = Diffusion(cfg.diffusion_steps)
        self.opt = torch.optim.AdamW(self.net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
        self.ema = EMA(self.net.state_dict(), cfg.ema_decay)
        self.gen = torch.Generator().manual_seed(cfg.seed)
        self.step = 0
        self.model = self.net
        if self.world > 1:
            self.model = torch.nn.parallel.DistributedDataParallel(self.net)
        self._resume()

    # ------------------------------------------------------------ state
    def _warm_start(self, folder: str) -> None:
        """Start from a trained checkpoint's weights (not its optimizer or step count): the data's
        normalisation is recomputed (unless init_stats), so a model can follow re-imported data
        without starting over."""
        motor = load_checkpoint(folder)
        # a persona network may start from a base without persona conditions (or blending): their
        # embedders start at zero, so the start is the base computation
        same = replace(self.cfg.model, persona=motor.net.cfg.persona, blend=motor.net.cfg.blend)
        if motor.net.cfg != same or (motor.net.cfg.persona and not self.cfg.model.persona):
            raise ValueError(f"init checkpoint {folder} has model {motor.net.cfg}, the config asks for {self.cfg.model}; "
                             "warm start needs the same architecture")
        missing, unexpected = self.net.load_state_dict(motor.net.state_dict(), strict=False)
        assert not unexpected and all(k.startswith("persona.") for k in missing), (missing, unexpected)

    def _resume(self) -> None:
        saved = read_state(self.out / "checkpoint", self.state_dir)
        if saved is None:
            return
        st, meta, tensors = saved
        self.net.load_state_dict({k[4:]: v for k, v in tensors.items() if k.startswith("net.")})
        self.ema.shadow = {k[4:]: v for k, v in tensors.items() if k.startswith("ema.")}
        self.opt.load_state_dict(_unflatten_optimizer(tensors, meta["optimizer"]))
        self.gen.set_state(tensors["rng.data"])
        torch.set_rng_state(tensors["rng.torch"])
        self.step = meta["step"]
        if self.rank == 0:
            _drop_logged_after(self.out / "metrics.jsonl", self.step)  # those steps are trained again
            print(f"resumed from {st} at step {self.step}", flush=True)

    def save_state(self) -> None:
        """The training state, then the checkpoint, each swapped in whole (io/atomic.py): a kill at
        any instant leaves a complete state to resume from and a complete checkpoint."""
        if self.rank != 0:
            return
        opt_t, opt_meta = _flatten_optimizer(self.opt)
        tensors = {**{f"net.{k}": v for k, v in self.net.state_dict().items()},
                   **{f"ema.{k}": v for k, v in self.ema.shadow.items()}, **opt_t,
                   "rng.data": self.gen.get_state(), "rng.torch": torch.get_rng_state()}

        def fill(tmp: Path) -> None:
            save_file({k: v.contiguous() for k, v in tensors.items()}, str(tmp / "state.safetensors"))
            (tmp / "state.json").write_text(json.dumps({"step": self.step, "optimizer": opt_meta}))  # last: marks it complete

        replace_folder(self.state_dir, fill, _state_complete)
        self.export(self.out / "checkpoint")

    def export(self, folder: Path, card: str | None = None, extra: dict | None = None) -> Path:
        with torch.random.fork_rng():  # building the EMA network draws random init: not from the training's stream
            ema_net = Denoiser(self.cfg.model)
        ema_net.load_state_dict(self.ema.shadow)
        info = {"name": self.cfg.name, "licence": self.cfg.licence, "trained_steps": self.step,
                "training_data": [str(p.name) for p in self.cache_paths], "train_config": _jsonable(asdict(self.cfg)),
                **(extra or {})}
        return save_checkpoint(folder, ema_net, self.norm, info, card, self.cfg.diffusion_steps)

    # ------------------------------------------------------------ loop
    def train_step(self) -> dict[str, float]:
        cfg = self.cfg
        self.net.train()
        x, shapes, clip = self.ds.sample_indexed(cfg.batch, self.gen)
        t = torch.randint(self.diffusion.T, (cfg.batch,), generator=self.gen)
        noise = torch.randn(cfg.batch, cfg.segment.frames, x.shape[-1], generator=self.gen)
        persona = self.persona_batch(x, shapes, clip) if cfg.model.persona else None
        # the state the network continues from: the window's own, or (persona_swap) another's
        swapped = self.swapped_initial(x, shapes, clip, persona) if self.pool is not None else None
        if self.world > 1:  # every rank drew the global batch; keep this rank's slice
            sl = slice(self.rank * cfg.batch // self.world, (self.rank + 1) * cfg.batch // self.world)
            x, shapes, t, noise = x[sl], shapes[sl], t[sl], noise[sl]
            persona = persona.select(sl) if persona is not None else None
            swapped = swapped[sl] if swapped is not None else None
        xn = self.norm.encode(x)
        x_init_n = xn[:, 0] if swapped is None else self.norm.encode(swapped)
        target_n = xn[:, 1:]
        x_t = self.diffusion.q_sample(target_n, t, noise)
        pred = self.model(t, x_t, x_init_n, None, persona)
        losses = motion_loss(pred, target_n, x[:, 0], shapes, self.norm, cfg.fk_weight, cfg.fkv_weight)
        for g in self.opt.param_groups:
            g["lr"] = self.lr_at(self.step)
        self.opt.zero_grad(set_to_none=True)
        losses["loss"].backward()
        self.opt.step()
        self.step += 1
        self.ema.update(self.net.state_dict(), active=self.step > cfg.ema_start)
        out = torch.stack([v.detach() for v in losses.values()])
        if self.world > 1:  # report the global batch's losses, not this rank's half
            dist.all_reduce(out)
            out /= self.world
        return {k: float(v) for k, v in zip(losses, out)}

    def persona_batch(self, x: torch.Tensor, shapes: torch.Tensor, clip: torch.Tensor) -> PersonaCond:
        """The windows' own conditions: a training description of the clip's style, the body shape
        the window was posed on, the trajectory its root takes; each left out at persona_dropout,
        and the text always where the clip has no style (DeepMimic)."""
        text, has_text = self.texts.draw(clip, self.gen)
        present = torch.rand(len(x), 3, generator=self.gen) >= self.cfg.persona_dropout
        present[:, 0] &= has_text
        for name in self.cfg.persona_without:
            present[:, CONDITIONS.index(name)] = False
        return PersonaCond(text, shapes, trajectory_of(x[:, 1:]), present)

    def swapped_initial(self, x: torch.Tensor, shapes: torch.Tensor, clip: torch.Tensor, persona: PersonaCond) -> torch.Tensor:
        """The initial states the network continues from (B, 267): a persona_swap share of the
        windows with a text get a feet-matched state of another style (see persona_swap)."""
        x0 = x[:, 0].clone()
        swap = (torch.rand(len(x), generator=self.gen) < self.cfg.persona_swap) & persona.present[:, 0]
        rows = swap.nonzero()[:, 0]
        if len(rows):
            style = self.texts.clip_style[clip[rows]]
            allowed = self.pool_style[None] != style[:, None]
            pick = self.pool.partners(self.norm.encode(x0[rows]), clip[rows], self.cfg.persona_neighbours, self.gen, allowed)
            xo, _ = self.ds.windows(self.ds.window_starts[self.pool.index[pick]], self.gen, shapes=shapes[rows],
                                    mirror=self.pool.mirror[pick])
            x0[rows] = xo[:, 0]
        return x0

    def lr_at(self, step: int) -> float:
        cfg = self.cfg
        if step < cfg.warmup:
            return cfg.lr * (step + 1) / cfg.warmup
        p = min(1.0, (step - cfg.warmup) / max(1, cfg.steps - cfg.warmup))
        return cfg.lr * (cfg.lr_final_ratio + (1 - cfg.lr_final_ratio) * 0.5 * (1 + math.cos(math.pi * p)))

    def run(self, steps: int | None = None) -> list[dict]:
        from tqdm import tqdm

        cfg = self.cfg
        end = steps if steps is not None else (cfg.stop_at or cfg.steps)
        self.out.mkdir(parents=True, exist_ok=True)
        if self.rank == 0:
            (self.out / "config.json").write_text(json.dumps(_jsonable(asdict(cfg)), indent=1))
        log_path = self.out / "metrics.jsonl"
        history = []
        bar = tqdm(total=end, initial=self.step, desc="train", unit="step", disable=not self.progress or self.rank != 0,
                   mininterval=5.0)
        t0, s0 = time.time(), self.step
        window: list[dict] = []
        while self.step < end:
            m = self.train_step()
            m["step"] = self.step
            history.append(m)
            window.append(m)
            bar.update(1)
            if self.step % cfg.log_every == 0 or self.step == end:
                rate = (self.step - s0) / max(time.time() - t0, 1e-9)
                # log the mean over the interval: single-step losses are too noisy to read
                m = {k: sum(w[k] for w in window) / len(window) for k in ("loss", "simple", "fk", "fkv")}
                m.update(step=self.step, steps_per_s=rate, elapsed_s=time.time() - t0)
                window = []
                bar.set_postfix(loss=f"{m['loss']:.4f}", sps=f"{rate:.2f}")
                if self.rank == 0:
                    with open(log_path, "a") as f:
                        f.write(json.dumps(m) + "\n")
            if self.step % cfg.checkpoint_every == 0 or self.step == end:
                self.save_state()
                if self.rank == 0:
                    plot_losses(log_path, self.out / "loss.png")
        bar.close()
        if self.world > 1:
            dist.barrier()  # no rank leaves while rank 0 still writes the checkpoint and plot
        return history


def read_state(checkpoint: Path, state_dir: Path):
    """(folder, meta, tensors) of a run's saved training state, or None for a new run. A kill may
    have landed inside a save: the newest complete copies of both folders are taken back first."""
    recover_folder(checkpoint, checkpoint_complete)
    st = recover_folder(state_dir, _state_complete)
    if st is None:
        return None
    return st, json.loads((st / "state.json").read_text()), load_file(str(st / "state.safetensors"))


def _state_complete(folder: Path) -> bool:
    """A training state whose files were all written (state.json is written last)."""
    try:
        json.loads((folder / "state.json").read_text())
    except (OSError, ValueError):
        return False
    return (folder / "state.safetensors").exists()


def _drop_logged_after(log: Path, step: int) -> None:
    """Keep the metric lines up to `step`: a resumed run logs the later ones again."""
    if not log.exists():
        return
    lines = [ln for ln in log.read_text().splitlines() if ln.strip()]
    keep = []
    for ln in lines:
        try:
            if json.loads(ln)["step"] <= step:
                keep.append(ln)
        except (ValueError, KeyError):
            pass  # a line cut by the kill
    if len(keep) != len(lines):
        write_file(log, lambda tmp: tmp.write_text("".join(k + "\n" for k in keep)))


def _jsonable(d):
    if isinstance(d, dict):
        return {k: _jsonable(v) for k, v in d.items()}
    if isinstance(d, (list, tuple)):
        return [_jsonable(v) for v in d]
    return d


def plot_losses(log_path: Path, png: Path, keys=("loss", "simple", "fk", "fkv")) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not Path(log_path).exists():  # a checkpoint before the first logged step (checkpoint_every < log_every)
        return
    rows = [json.loads(l) for l in Path(log_path).read_text().splitlines() if l.strip()]
    if not rows:
        return
    fig, ax = plt.subplots(figsize=(7, 4))
    for key in keys:
        ax.plot([r["step"] for r in rows], [r[key] for r in rows], label=key)
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    write_file(png, lambda tmp: fig.savefig(tmp, dpi=90, format="png"))
    plt.close(fig)
