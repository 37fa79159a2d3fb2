"""Training of the few-step samplers (model/fewstep.py), both warm-started from a base checkpoint
and on the same footing (data, batch, steps, generator learning rate, chains, EMA, losses):

emdm (EMDM §3, Eq. 4-12, supplementary C.3): per iteration the discriminator takes a step on
softplus(-D(real)) + softplus(D(fake)) + gamma/2 |grad_x D(real)|^2 (R1), then the generator
takes a step on softplus(-D(fake)) + R L_geo. Pairs (t, t_prev) are the steps of the chains of
1, 2 and 4 trailing steps, drawn uniformly; the fake x_prev is the posterior sample from the
generator's x0 estimate.

consistency (consistency distillation, as MotionLCM does): from x_t at a random t, one DDIM step
of the frozen 50-step teacher reaches t_prev = t - skip (the clean segment below 0); the student's
x0 estimate at t is pulled toward the target network's (an EMA of the student) estimate at t_prev,
or toward the teacher's own at the clean end. The distance is L_geo with the target in place of
the data: the same terms as EMDM's.

L_geo = L_recon + lambda (L_pos + L_vel + L_foot): our base's loss (normalised-state MSE, FK
positions, FK velocities; train/losses.py) plus EMDM's foot-contact term (Eq. 9).

Resumable like `train`: the whole state (networks, optimizers, EMAs, random streams) is swapped
in whole every `checkpoint_every` steps, and the exported generator is a checkpoint folder whose
config names its sampler and the base it came from.
"""
from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
import torch.nn.functional as F
from safetensors.torch import save_file

from ..data.cache import MotionCache
from .. import config
from ..data.dataset import SegmentConfig, SegmentDataset
from ..io.atomic import replace_folder
from ..model.adaptor import base_fingerprint
from ..model.checkpoint import load_checkpoint, save_checkpoint
from ..model.denoiser import Denoiser, DenoiserConfig
from ..model.fewstep import (FEW_STEPS, Discriminator, abar_at, forward_pair, posterior_sample,
                             trailing_timesteps)
from .losses import foot_loss, motion_loss
from .trainer import (EMA, LICENCE_NOTE, _drop_logged_after, _flatten_optimizer, _jsonable, _state_complete,
                      _unflatten_optimizer, plot_losses, read_state, resolve_caches)

METHODS = ("emdm", "consistency")


@dataclass
class FewStepConfig:
    method: str = "emdm"  # or "consistency"
    base: str = "models/primal-bandai"  # the checkpoint both start from (and the teacher)
    data: list[str] = field(default_factory=lambda: ["dataset-1", "dataset-2"])
    out: str = "runs/emdm"
    steps: int = 4000
    batch: int = 64  # EMDM's
    lr: float = 5e-5  # generator (both methods)
    lr_d: float = 1.25e-4  # EMDM's discriminator
    r1_gamma: float = 0.02  # EMDM's
    geo_weight: float = 10.0  # R of EMDM Eq. 12
    geo_terms: float = 1.0  # lambda of EMDM Eq. 11
    fk_weight: float = 20.0  # as the base trains: per m^2
    fkv_weight: float = 0.2  # per (m/s)^2
    foot_weight: float = 1.0  # per (m/s)^2 of planted-foot speed
    latent: int = 64  # EMDM's z
    chains: list[int] = field(default_factory=lambda: list(FEW_STEPS))
    default_steps: int = 2  # what the runtime samples with unless told otherwise
    skip: int = 4  # consistency: teacher timesteps per solver step
    target_decay: float = 0.95  # consistency: the target network's EMA (MotionLCM's)
    disc_hidden: int = 512
    disc_depth: int = 5
    ema_decay: float = 0.999
    ema_start: int = 200
    checkpoint_every: int = 250
    log_every: int = 25
    seed: int = 0
    threads: int = 0
    segment: SegmentConfig = field(default_factory=SegmentConfig)
    name: str = ""  # default: the base's name + "-" + method
    licence: str = LICENCE_NOTE

    @staticmethod
    def from_dict(d: dict) -> "FewStepConfig":
        return config.from_dict(FewStepConfig, d, "few-step config").validated()

    def validated(self) -> "FewStepConfig":
        cfg = self
        if cfg.method not in METHODS:
            raise ValueError(f"few-step config 'method' must be one of {METHODS}, got {cfg.method!r}")
        if not cfg.chains or any(c not in FEW_STEPS for c in cfg.chains) or cfg.default_steps not in cfg.chains:
            raise ValueError(f"few-step 'chains' must be a subset of {FEW_STEPS} holding 'default_steps'")
        return cfg


def chain_pairs(T: int, chains: list[int]) -> torch.Tensor:
    """Every (t, t_prev) step of the trailing chains, each once: (P, 2) long, t_prev = -1 clean."""
    pairs = set()
    for s in chains:
        ts = trailing_timesteps(T, s).tolist()
        pairs.update((ts[k], ts[k - 1] if k else -1) for k in range(s))
    return torch.tensor(sorted(pairs), dtype=torch.long)


class FewStepTrainer:
    def __init__(self, cfg: FewStepConfig, progress: bool = True):
        self.cfg, self.progress = cfg, progress
        if cfg.threads:
            torch.set_num_threads(cfg.threads)
        self.out = Path(cfg.out)
        self.state_dir = self.out / "train_state"
        base = load_checkpoint(cfg.base)
        self.base_name, self.base_fp = base.name, base_fingerprint(base.net)
        self.norm, self.diffusion = base.norm, base.diffusion
        self.cache_paths = resolve_caches(cfg.data)
        self.ds = SegmentDataset([MotionCache.load(p) for p in self.cache_paths], cfg.segment)
        torch.manual_seed(cfg.seed)
        latent = cfg.latent if cfg.method == "emdm" else 0
        self.gcfg = DenoiserConfig(**{**base.net.cfg.to_dict(), "latent": latent, "dropout": 0.0})
        self.net = Denoiser(self.gcfg)
        missing, unexpected = self.net.load_state_dict(base.net.state_dict(), strict=False)
        assert not unexpected and all(k.startswith("z_mlp.") for k in missing), (missing, unexpected)
        self.teacher = base.net.eval().requires_grad_(False)
        self.opt = torch.optim.AdamW(self.net.parameters(), lr=cfg.lr, weight_decay=0.0)
        self.ema = EMA(self.net.state_dict(), cfg.ema_decay)
        if cfg.method == "emdm":
            N, D = self.gcfg.frames, self.gcfg.state_dim
            self.disc = Discriminator(N, D, cfg.disc_hidden, cfg.disc_depth)
            self.opt_d = torch.optim.Adam(self.disc.parameters(), lr=cfg.lr_d, betas=(0.5, 0.9))
            self.pairs = chain_pairs(self.diffusion.T, cfg.chains)
        else:
            self.target = EMA(self.net.state_dict(), cfg.target_decay)
            with torch.random.fork_rng():
                self.target_net = Denoiser(self.gcfg).eval().requires_grad_(False)
        self.gen = torch.Generator().manual_seed(cfg.seed)
        self.step = 0
        self._resume()

    # ------------------------------------------------------------ state
    def _tensors(self) -> dict[str, torch.Tensor]:
        t = {**{f"net.{k}": v for k, v in self.net.state_dict().items()},
             **{f"ema.{k}": v for k, v in self.ema.shadow.items()}}
        if self.cfg.method == "emdm":
            t.update({f"disc.{k}": v for k, v in self.disc.state_dict().items()})
        else:
            t.update({f"target.{k}": v for k, v in self.target.shadow.items()})
        return t

    def _optimizers(self) -> dict[str, torch.optim.Optimizer]:
        return {"g": self.opt, **({"d": self.opt_d} if self.cfg.method == "emdm" else {})}

    def _resume(self) -> None:
        saved = read_state(self.out / "checkpoint", self.state_dir)
        if saved is None:
            return
        st, meta, tensors = saved
        if meta.get("method") != self.cfg.method:
            raise ValueError(f"{st}: the saved run trains {meta.get('method')!r}, this config {self.cfg.method!r}; "
                             "use another 'out' folder")
        pick = lambda p: {k[len(p):]: v for k, v in tensors.items() if k.startswith(p)}  # noqa: E731
        self.net.load_state_dict(pick("net."))
        self.ema.shadow = pick("ema.")
        if self.cfg.method == "emdm":
            self.disc.load_state_dict(pick("disc."))
        else:
            self.target.shadow = pick("target.")
        for name, opt in self._optimizers().items():
            opt.load_state_dict(_unflatten_optimizer(pick(f"opt_{name}."), meta["optimizers"][name]))
        self.gen.set_state(tensors["rng.data"])
        torch.set_rng_state(tensors["rng.torch"])
        self.step = meta["step"]
        _drop_logged_after(self.out / "metrics.jsonl", self.step)
        print(f"resumed from {st} at step {self.step}", flush=True)

    def save_state(self) -> None:
        tensors, metas = self._tensors(), {}
        for name, opt in self._optimizers().items():
            t, metas[name] = _flatten_optimizer(opt)
            tensors.update({f"opt_{name}.{k}": v for k, v in t.items()})
        tensors["rng.data"], tensors["rng.torch"] = self.gen.get_state(), torch.get_rng_state()

        def fill(tmp: Path) -> None:
            save_file({k: v.contiguous() for k, v in tensors.items()}, str(tmp / "state.safetensors"))
            (tmp / "state.json").write_text(json.dumps({"step": self.step, "method": self.cfg.method,
                                                        "optimizers": metas}))

        replace_folder(self.state_dir, fill, _state_complete)
        self.export(self.out / "checkpoint")

    def export(self, folder: Path, card: str | None = None, extra: dict | None = None, half: bool = False) -> Path:
        cfg = self.cfg
        with torch.random.fork_rng():
            net = Denoiser(self.gcfg)
        net.load_state_dict(self.ema.shadow)
        info = {"name": cfg.name or f"{self.base_name}-{cfg.method}", "licence": cfg.licence,
                "trained_steps": self.step, "training_data": [p.name for p in self.cache_paths],
                "sampler": {"kind": cfg.method, "steps": cfg.default_steps, "chains": list(cfg.chains),
                            "base": self.base_name, "base_fingerprint": self.base_fp},
                "train_config": _jsonable(asdict(cfg)), **(extra or {})}
        return save_checkpoint(folder, net, self.norm, info, card, self.diffusion.T, half=half)

    # ------------------------------------------------------------ losses
    def _batch(self):
        cfg = self.cfg
        x, shapes = self.ds.sample(cfg.batch, self.gen)
        xn = self.norm.encode(x)
        return x[:, 0], shapes, xn[:, 0], xn[:, 1:]

    def _geo(self, pred_n, target_n, x_init, shapes) -> dict[str, torch.Tensor]:
        cfg = self.cfg
        m = motion_loss(pred_n, target_n, x_init, shapes, self.norm, cfg.fk_weight, cfg.fkv_weight)
        foot = foot_loss(pred_n, target_n, x_init, shapes, self.norm)
        # motion_loss's total is recon + weighted pos + vel; lambda scales the geometric terms
        geo = m["simple"] + cfg.geo_terms * (m["loss"] - m["simple"] + cfg.foot_weight * foot)
        return {"geo": geo, "simple": m["simple"], "fk": m["fk"], "fkv": m["fkv"], "foot": foot.detach()}

    def _randn(self, *shape) -> torch.Tensor:
        return torch.randn(*shape, generator=self.gen)

    def emdm_step(self) -> dict[str, float]:
        cfg = self.cfg
        x_init, shapes, c, target_n = self._batch()
        B = len(c)
        pair = self.pairs[torch.randint(len(self.pairs), (B,), generator=self.gen)]
        t, t_prev = pair[:, 0], pair[:, 1]
        ab_t, ab_prev = abar_at(self.diffusion, t), abar_at(self.diffusion, t_prev)
        x_prev, x_t = forward_pair(ab_t, ab_prev, target_n, self._randn(*target_n.shape), self._randn(*target_n.shape))
        z = self._randn(B, cfg.latent)
        post_noise = self._randn(*target_n.shape)
        # discriminator: real pairs against the generator's, R1 on the real ones
        with torch.no_grad():
            fake = posterior_sample(ab_t, ab_prev, self.net(t, x_t, c, z), x_t, post_noise)
        real = x_prev.detach().requires_grad_(True)
        d_real = self.disc(real, x_t, c, t, t_prev)
        d_fake = self.disc(fake, x_t, c, t, t_prev)
        grad, = torch.autograd.grad(d_real.sum(), real, create_graph=True)
        r1 = grad.flatten(1).square().sum(-1).mean()
        loss_d = F.softplus(-d_real).mean() + F.softplus(d_fake).mean() + cfg.r1_gamma / 2 * r1
        self.opt_d.zero_grad(set_to_none=True)
        loss_d.backward()
        self.opt_d.step()
        # generator: fool the discriminator, keep the geometric losses
        self.disc.requires_grad_(False)
        x0_hat = self.net(t, x_t, c, z)
        fake = posterior_sample(ab_t, ab_prev, x0_hat, x_t, post_noise)
        adv = F.softplus(-self.disc(fake, x_t, c, t, t_prev)).mean()
        geo = self._geo(x0_hat, target_n, x_init, shapes)
        loss = adv + cfg.geo_weight * geo["geo"]
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        self.disc.requires_grad_(True)
        return {"loss": float(loss.detach()), "adv": float(adv.detach()), "loss_d": float(loss_d.detach()),
                "r1": float(r1.detach()), "d_real": float(d_real.detach().mean()), "d_fake": float(d_fake.detach().mean()),
                **{k: float(v.detach()) for k, v in geo.items()}}

    def consistency_step(self) -> dict[str, float]:
        cfg = self.cfg
        x_init, shapes, c, target_n = self._batch()
        B = len(c)
        t = torch.randint(self.diffusion.T, (B,), generator=self.gen)
        t_prev = (t - cfg.skip).clamp(min=-1)
        ab_t, ab_prev = abar_at(self.diffusion, t), abar_at(self.diffusion, t_prev)
        rows = lambda v: v.float().view(-1, 1, 1)  # noqa: E731
        x_t = rows(ab_t.sqrt()) * target_n + rows((1 - ab_t).sqrt()) * self._randn(*target_n.shape)
        with torch.no_grad():
            x0_teacher = self.teacher(t, x_t, c)
            eps = (x_t - rows(ab_t.sqrt()) * x0_teacher) / rows((1 - ab_t).sqrt())
            x_prev = rows(ab_prev.sqrt()) * x0_teacher + rows((1 - ab_prev).sqrt()) * eps  # DDIM step
            self.target_net.load_state_dict(self.target.shadow)
            clean = t_prev < 0
            goal = self.target_net(t_prev.clamp(min=0), x_prev, c)
            goal = torch.where(clean[:, None, None], x_prev, goal)  # f(x, clean) = x
        pred = self.net(t, x_t, c)
        geo = self._geo(pred, goal, x_init, shapes)
        loss = cfg.geo_weight * geo["geo"]
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        self.target.update(self.net.state_dict(), active=True)
        return {"loss": float(loss.detach()), **{k: float(v.detach()) for k, v in geo.items()}}

    def train_step(self) -> dict[str, float]:
        self.net.train()
        m = self.emdm_step() if self.cfg.method == "emdm" else self.consistency_step()
        self.step += 1
        self.ema.update(self.net.state_dict(), active=self.step > self.cfg.ema_start)
        return m

    def run(self, steps: int | None = None) -> list[dict]:
        cfg = self.cfg
        end = steps if steps is not None else cfg.steps
        self.out.mkdir(parents=True, exist_ok=True)
        (self.out / "config.json").write_text(json.dumps(_jsonable(asdict(cfg)), indent=1))
        log = self.out / "metrics.jsonl"
        t0, s0, window, history = time.time(), self.step, [], []
        while self.step < end:
            window.append(self.train_step())
            history.append(window[-1])
            if self.step % cfg.log_every == 0 or self.step == end:
                m = {k: sum(w[k] for w in window) / len(window) for k in window[0]}
                rate = (self.step - s0) / max(time.time() - t0, 1e-9)
                m.update(step=self.step, steps_per_s=rate, elapsed_s=time.time() - t0)
                window = []
                with open(log, "a") as f:
                    f.write(json.dumps(m) + "\n")
                if self.progress:
                    eta = (end - self.step) / max(rate, 1e-9)
                    print(f"{cfg.method} step {self.step}/{end} loss {m['loss']:.4f} geo {m['geo']:.4f} "
                          f"{rate:.2f} steps/s, {eta / 60:.0f} min left", flush=True)
            if self.step % cfg.checkpoint_every == 0 or self.step == end:
                self.save_state()
                plot_losses(log, self.out / "loss.png", ("loss", "geo", "simple", "fk", "foot"))
        return history
