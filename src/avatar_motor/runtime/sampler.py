"""The sampler (DESIGN §5): network + reverse diffusion + guidance for a batch of segments, in each
segment's canonical frame. It reads a SegmentBatch and the canonical initial states and returns
the decoded segments (float64, before post-processing); it changes no avatar. Steering impulses
condition the network, gradient guidance steers the denoised estimate, and adaptors (action
labels, styles, reaching targets) replace the base network for the avatars they steer."""
from __future__ import annotations

import dataclasses
import logging
import weakref

import torch

from ..body import rotations as rot
from ..body.motion_state import SLICES, STATE_DIM, Transform
from ..model.checkpoint import Motor
from ..model.persona import CONDITIONS, TEXT_DIM, TRAJ_FEATURES, PersonaCond
from .guidance import facing_loss_and_grad, facing_of, goal_trajectory, move_loss_and_grad, path_loss_and_grad
from ..model import fewstep
from ..model.bf16 import bf16_denoiser
from ..model.onnx import onnx_denoiser
from .stages import SegmentBatch

BACKENDS = ("torch", "onnxruntime")


def bfloat16_units() -> bool:
    """This CPU multiplies bfloat16 matrices in hardware (AVX-512 BF16 or AMX). Without, bfloat16
    ran 2-9x slower than float32 (an AVX2 host: model card of the EMDM generator)."""
    cpu = torch.cpu
    return bool(getattr(cpu, "_is_avx512_bf16_supported", lambda: False)()
                or getattr(cpu, "_is_amx_tile_supported", lambda: False)())


class BatchSwitch:
    """The network in bfloat16, where this CPU's bfloat16 matrix units pay (RuntimeConfig.bfloat16_from):
    batches of fewer than `rows` rows as `small` runs it (model/bf16.py: bfloat16 linear weights,
    traced), larger ones as torch runs `net` under bfloat16 autocast. `float32` is the network in
    float32 (ONNX Runtime or torch), for what must not change (physics mode's candidates). The
    output is float32 in every case."""

    def __init__(self, float32, net, rows: int, small=None):
        self.float32, self.net, self.rows = float32, net, rows
        self.small = float32 if small is None else small

    def __call__(self, t, x_t, *rest):
        if len(x_t) < self.rows:
            return self.small(t, x_t, *rest)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            return self.net(t, x_t, *rest).float()


log = logging.getLogger("avatar_motor.runtime")

# the joints that carry a steering impulse: the whole body. The trunk alone (as in the
# forward_run preset) was the default until measured (eval control, 45 x 3 s, impulse 1.5):
# velocity error 0.503 -> 0.420, facing 0.088 -> 0.076, ASR over unguided +0.026 -> +0.039; and 8
# avatars idling 1 s, then a 1.2 m/s goal for 10 s: 0.29 -> 0.78 m/s mean (the trunk alone let most
# of them shuffle); at impulse 2 or more either way the walk lurches segment by segment
STEER_JOINTS = list(range(22))


# DDPM steps for an adaptor's avatars when the runtime's model is a few-step one (the adaptor
# runs on its base, as trained: the runtime's 8-step default before few-step sampling)
ADAPTOR_STEPS = 8


TEACHER = -2  # the group of rows sampled by a few-step model's teacher (Sampler.sample)


def _teacher(motor: Motor) -> Motor | None:
    """A few-step model's DDPM base (checkpoint.load_base), loaded once per model object; None,
    with a log line, when it is not beside the model: impulse presets then run on the model itself."""
    if motor.net not in _TEACHERS:  # keyed by the network: a Motor (a dataclass) is not hashable
        from ..model.checkpoint import CheckpointError, load_base
        try:
            _TEACHERS[motor.net] = load_base(motor)
        except CheckpointError as e:
            log.warning("impulse presets run on the few-step model itself: %s", e)
            _TEACHERS[motor.net] = None
    return _TEACHERS[motor.net]


_TEACHERS: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def _subset(batch: SegmentBatch, rows: torch.Tensor) -> SegmentBatch:
    """The rows `rows` of a batch (tensors indexed, lists picked; a value for the whole batch kept)."""
    picked = {}
    for f in dataclasses.fields(batch):
        v = getattr(batch, f.name)
        picked[f.name] = v[rows] if torch.is_tensor(v) else [v[int(k)] for k in rows] if isinstance(v, list) else v
    return SegmentBatch(**picked)


def _local_goals(goals: list, Rt: torch.Tensor) -> torch.Tensor:
    """World goal vectors (3,) or None per avatar -> (B, 3) in each body's canonical frame (None: 0)."""
    z3 = torch.zeros(3, dtype=torch.float64)
    return (Rt @ torch.stack([z3 if g is None else g.double() for g in goals])[..., None])[..., 0]


class Cancelled(Exception):
    """A batch stopped because every avatar in it was cut meanwhile."""


class Sampler:
    def __init__(self, motor: Motor, cfg, adaptors=None):
        """cfg: the RuntimeConfig (steps, eta, steering and guidance weights); adaptors:
        AdaptedDenoisers on motor's (base) network, a list, one, or None. self.cfg is cfg with its
        steps resolved (0: the model's own default)."""
        self.kind = motor.sampler["kind"]
        steps = cfg.steps or motor.sampler["steps"]
        fewstep.check_steps(self.kind, steps)
        cfg = dataclasses.replace(cfg, steps=steps)
        adaptors = [] if adaptors is None else list(adaptors) if isinstance(adaptors, (list, tuple)) else [adaptors]
        self.motor, self.cfg, self.adaptors = motor, cfg, adaptors
        for ad in adaptors:
            if self.kind != "ddpm" and ad.base_fingerprint != motor.sampler.get("base_fingerprint"):
                raise ValueError(f"an adaptor was trained on other base weights than {motor.name}'s base "
                                 f"{motor.sampler.get('base')!r}; retrain it on that base")
        if cfg.backend not in BACKENDS:
            raise ValueError(f"runtime backend must be one of {BACKENDS}, got {cfg.backend!r}")
        # the base network as ONNX Runtime runs it (an adaptor's avatars use torch; so does a persona
        # network, whose persona conditions the exported graph does not take)
        self.net = (onnx_denoiser(motor.net, cfg.int8_weights) if cfg.backend == "onnxruntime" and not motor.net.cfg.persona
                    else motor.net)
        if cfg.bfloat16_from > 0 and bfloat16_units():
            # (int8 weights asked for: small batches keep them)
            small = None if cfg.int8_weights or motor.net.cfg.persona else bf16_denoiser(motor.net)
            self.net = BatchSwitch(self.net, motor.net, cfg.bfloat16_from, small)
        # a few-step model's teacher for the segments after an impulse preset (impulse_teacher)
        self.teacher = None  # (in float32: its batches are the few avatars just after a preset)
        if self.kind != "ddpm" and cfg.impulse_teacher > 0:
            base = _teacher(motor)
            # the teacher's rows are encoded and decoded with this model's normalisation, which
            # distillation keeps from its base
            if base is not None and torch.equal(base.norm.mean, motor.norm.mean) and torch.equal(base.norm.std, motor.norm.std):
                self.teacher = onnx_denoiser(base.net, cfg.int8_weights) if cfg.backend == "onnxruntime" else base.net
            elif base is not None:
                log.warning("impulse presets run on %s itself: its base normalises states otherwise", motor.name)

    def sample(self, batch: SegmentBatch, x0c: torch.Tensor, tf: Transform, cancelled=None) -> torch.Tensor:
        """Segments (B, N, 267), float32, in the canonical frames whose world transforms are tf, from
        the canonical initial states x0c (B, 267). cancelled() -> True stops between network calls
        (raises Cancelled): the batch is no longer wanted.

        The avatars an adaptor steers are sampled as it was trained: on its base with DDPM (with a
        few-step model, ADAPTOR_STEPS), one batch per adaptor; so are, on the base network itself,
        a few-step model's avatars whose batch row asks for its teacher (after an impulse preset);
        the others with the model's own sampler. Rows are independent, so in float32 the split
        changes no avatar's motion (in bfloat16 a row depends on its batch by millimetres)."""
        taught = [self.teacher is not None and bool(batch.teacher and batch.teacher[k]) and ad is None
                  for k, ad in enumerate(batch.adaptors)]
        groups = sorted({k for k in batch.adaptors if k is not None}) + ([TEACHER] if any(taught) else [])
        if not groups:
            return self._sample(batch, x0c, tf, cancelled, self.kind == "ddpm", None)
        which = torch.tensor([TEACHER if t else -1 if k is None else k for k, t in zip(batch.adaptors, taught)])
        out = torch.empty(len(batch), self.motor.net.cfg.frames, STATE_DIM)
        for k in [-1, *groups]:
            rows = (which == k).nonzero()[:, 0]
            if len(rows):
                out[rows] = self._sample(_subset(batch, rows), x0c[rows], Transform(tf.R[rows], tf.t[rows]), cancelled,
                                         k != -1 or self.kind == "ddpm",
                                         self.adaptors[k] if k >= 0 else TEACHER if k == TEACHER else None)
        return out

    def _sample(self, batch: SegmentBatch, x0c: torch.Tensor, tf: Transform, cancelled, ddpm: bool, adaptor) -> torch.Tensor:
        cfg, motor = self.cfg, self.motor
        Rt = tf.R.transpose(-1, -2)
        # the network sees the impulse in x0's velocities; the blending after it keeps the true x0
        x0_cond = x0c.clone()
        x0_cond[:, SLICES["velocities"]] += (batch.impulse_velocity @ Rt.transpose(-1, -2)).reshape(len(batch), 66)
        if cfg.steer_impulse > 0 or cfg.turn_impulse > 0:
            self._steer(x0_cond, batch.v_goal, batch.facing_goal, Rt)
        cond = motor.norm.encode(x0_cond.float())
        # guidance acts between steps: a one-step chain has none (its goals steer through _steer)
        steps = ADAPTOR_STEPS if ddpm and self.kind != "ddpm" else cfg.steps
        guide = self._guidance(batch.v_goal, batch.facing_goal, Rt.float(), x0c.float()) if steps > 1 else None
        N = motor.net.cfg.frames
        denoise = self._denoiser(batch, tf, cond, adaptor, x0c)
        if cancelled is not None:
            inner = denoise

            def denoise(x_t, t, z=None):
                if cancelled():
                    raise Cancelled
                return inner(x_t, t, z)
        shape = (len(batch), N, STATE_DIM)
        if ddpm:
            seg_n = motor.diffusion.sample(denoise, shape, steps, batch.gens, guide, cfg.eta)
        else:
            seg_n = fewstep.sample(self.kind, motor.diffusion, denoise, shape, cfg.steps, batch.gens, guide,
                                   motor.net.cfg.latent)
        return motor.norm.decode(seg_n)

    def _denoiser(self, batch: SegmentBatch, tf, cond, ad, x0c):
        """The base network; the teacher (ad TEACHER: the few-step model's DDPM base); or the adaptor
        ad with each avatar's controls (every row of the batch is one it steers)."""
        net = self.net
        if isinstance(net, BatchSwitch) and any(job is not None for job in batch.physics):
            # physics mode's candidates stay in float32: in bfloat16 the simulated bodies (with joint
            # limits) left them sooner and resampled, every frame instead of every 8 (16 avatars:
            # 25 against 33 frames/s each) though their realism read the same
            net = net.float32
        if isinstance(ad, int) and ad == TEACHER:
            teacher = self.teacher
            return lambda x_t, t, z=None: teacher(t, x_t, cond)
        if ad is None:
            if self.motor.net.cfg.persona:
                persona = self._persona(batch, tf, x0c)
                # classifier-free guidance on the text and on the trajectory, each against the same
                # conditions without it: c + sum_k (w_k - 1) (c - u_k), all passes in one batch; a row
                # without that condition has u_k = c and comes out unchanged
                scales = [(w, k) for w, k in ((self.cfg.persona_scale, 0), (self.cfg.trajectory_scale, 2))
                          if w != 1.0 and bool(persona.present[:, k].any())]
                if not scales:
                    return lambda x_t, t, z=None: net(t, x_t, cond, z, persona)
                n = 1 + len(scales)
                every = PersonaCond.cat([persona] + [persona.without(CONDITIONS[k]) for _, k in scales])
                cond_n = torch.cat([cond] * n)

                def guided(x_t, t, z=None):
                    z_n = None if z is None else torch.cat([z] * n)
                    out = net(torch.cat([t] * n), torch.cat([x_t] * n), cond_n, z_n, every).chunk(n)
                    c = out[0]
                    return c + sum((w - 1.0) * (c - u) for (w, _), u in zip(scales, out[1:]))
                return guided
            if self.motor.net.cfg.latent:
                return lambda x_t, t, z=None: net(t, x_t, cond, z)
            return lambda x_t, t, z=None: net(t, x_t, cond)
        scale = torch.tensor(batch.control_scales, dtype=torch.float32)
        if ad.cfg.control == "label":
            y = torch.tensor([lb if lb is not None else ad.null_label for lb in batch.labels])
        else:
            Rt = tf.R.transpose(-1, -2).float()
            y = torch.zeros(len(batch), 2)
            for k, tg in enumerate(batch.targets):
                if tg is not None:
                    local = Rt[k] @ (torch.tensor([tg[0], 0.0, tg[1]]) - tf.t[k].float())
                    y[k] = local[[0, 2]]
        s = scale[:, None, None]
        return lambda x_t, t, z=None: ad(t, x_t, cond, y, scale=s)

    def _persona(self, batch: SegmentBatch, tf, x0c: torch.Tensor) -> PersonaCond:
        """A persona network's conditions: each avatar's text (if it has a persona), its body shape,
        and, where a goal steers it, the trajectory toward that goal (guidance.goal_trajectory)."""
        B, N = len(batch), self.motor.net.cfg.frames
        texts = batch.personas or [None] * B
        has_text = torch.tensor([e is not None for e in texts])
        text = torch.stack([e if e is not None else torch.zeros(TEXT_DIM) for e in texts]).float()
        has_goal = torch.tensor([v is not None for v in batch.v_goal])
        traj = torch.zeros(B, N, TRAJ_FEATURES)
        if bool(has_goal.any()):
            Rt = tf.R.transpose(-1, -2)
            traj = goal_trajectory(x0c.double(), _local_goals(batch.v_goal, Rt), _local_goals(batch.facing_goal, Rt), N,
                                   self.cfg.trajectory_halflife).float()
        present = torch.stack((has_text, torch.ones(B, dtype=torch.bool), has_goal), 1)
        return PersonaCond(text, batch.shapes.float(), traj, present)

    def _steer(self, x0c: torch.Tensor, v_goals: list, f_goals: list, Rt: torch.Tensor) -> None:
        """Steering as an impulse (our addition): the network starts each segment already moving the
        way it should go. The body's initial velocity is moved toward the goal velocity
        (horizontally, by steer_impulse x the difference), and the body gets a yaw rate toward the
        facing goal (turn_impulse x the angle, rad/s), as velocities about the pelvis."""
        cfg = self.cfg
        B = len(x0c)
        has_v = torch.tensor([v is not None for v in v_goals])
        has_f = torch.tensor([f is not None for f in f_goals])
        if not bool(has_v.any() or has_f.any()):
            return
        vel = x0c[:, SLICES["velocities"]].view(B, 22, 3)
        J = x0c[:, SLICES["joints"]].view(B, 22, 3)
        g_v, g_f = _local_goals(v_goals, Rt), _local_goals(f_goals, Rt)
        z, _ = facing_of(x0c)
        angle = torch.atan2(z[:, 2] * g_f[:, 0] - z[:, 0] * g_f[:, 2], (z * g_f).sum(-1))  # about +Y, z -> goal
        angle = torch.where(has_f, angle, torch.zeros_like(angle))
        if cfg.steer_impulse > 0 and bool(has_v.any()):
            if cfg.steer_with_body > 0:  # back toward where the body faces (angle 0 without a facing goal)
                g_v = (rot.yaw_matrix(-cfg.steer_with_body * angle) @ g_v[..., None])[..., 0]
            dv = cfg.steer_impulse * (g_v - vel[:, STEER_JOINTS].mean(1))
            dv[:, 1] = 0.0
            vel[:, STEER_JOINTS] += torch.where(has_v[:, None], dv, torch.zeros_like(dv))[:, None]
        if cfg.turn_impulse > 0 and bool(has_f.any()):
            w = (cfg.turn_impulse * angle)[:, None]  # a signal to the network more than a physical rate
            r = J - J[:, :1]
            vel += torch.stack((w * r[..., 2], torch.zeros_like(r[..., 0]), -w * r[..., 0]), -1)

    def _guidance(self, v_goals: list, f_goals: list, Rt: torch.Tensor, x0c: torch.Tensor):
        cfg = self.cfg
        has_v = [v is not None for v in v_goals]
        has_f = [f is not None for f in f_goals]
        if not any(has_v) and not any(has_f):
            return None
        z = torch.zeros(3)
        v_goal = torch.stack([Rt[k] @ (v if v is not None else z) for k, v in enumerate(v_goals)])
        f_goal = torch.stack([Rt[k] @ (f if f is not None else z) for k, f in enumerate(f_goals)])
        on_v = torch.tensor(has_v, dtype=torch.float32)[:, None, None]
        wf = torch.tensor(has_f, dtype=torch.float32)[:, None, None] * cfg.facing_weight
        norm = self.motor.norm

        def guide(x0n):
            x = norm.decode(x0n)
            _, gv = move_loss_and_grad(x, v_goal)
            _, gp = path_loss_and_grad(x, x0c, v_goal)
            _, gf = facing_loss_and_grad(x, f_goal)
            step = on_v * (cfg.move_weight * gv + cfg.path_weight * gp) + wf * gf  # real units
            return norm.encode(x - step)

        return guide
