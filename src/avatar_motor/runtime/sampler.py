"""The sampler (DESIGN §5): network + reverse diffusion + guidance for a batch of segments, in each
segment's canonical frame. It reads a SegmentBatch and the canonical initial states and returns
the decoded segments (float64, before post-processing); it changes no avatar. Steering impulses
condition the network, gradient guidance steers the denoised estimate, and an adaptor (action
labels or reaching targets) replaces the base network for the avatars it steers."""
from __future__ import annotations

import torch

from ..body import rotations as rot
from ..body.motion_state import SLICES, STATE_DIM, Transform
from ..body.skeleton import JOINT_INDEX
from ..model.checkpoint import Motor
from .guidance import facing_loss_and_grad, facing_of, move_loss_and_grad, path_loss_and_grad
from ..model.onnx import onnx_denoiser
from .stages import SegmentBatch

BACKENDS = ("torch", "onnxruntime")

# the joints that carry a steering impulse: the whole body. The trunk alone (as in the
# forward_run preset) was the default until measured (eval control, 45 x 3 s, impulse 1.5):
# velocity error 0.503 -> 0.420, facing 0.088 -> 0.076, ASR over unguided +0.026 -> +0.039; and 8
# avatars idling 1 s, then a 1.2 m/s goal for 10 s: 0.29 -> 0.78 m/s mean (the trunk alone let most
# of them shuffle); at impulse 2 or more either way the walk lurches segment by segment
STEER_JOINTS = list(range(22))


class Cancelled(Exception):
    """A batch stopped because every avatar in it was cut meanwhile."""


class Sampler:
    def __init__(self, motor: Motor, cfg, adaptor=None):
        """cfg: the RuntimeConfig (steps, eta, steering and guidance weights); adaptor: an
        AdaptedDenoiser on motor's network, or None."""
        self.motor, self.cfg, self.adaptor = motor, cfg, adaptor
        if cfg.backend not in BACKENDS:
            raise ValueError(f"runtime backend must be one of {BACKENDS}, got {cfg.backend!r}")
        # the base network as ONNX Runtime runs it (an adaptor's avatars use torch)
        self.net = onnx_denoiser(motor.net) if cfg.backend == "onnxruntime" else motor.net

    def sample(self, batch: SegmentBatch, x0c: torch.Tensor, tf: Transform, cancelled=None) -> torch.Tensor:
        """Segments (B, N, 267) in the canonical frames whose world transforms are tf, from the
        canonical initial states x0c (B, 267). cancelled() -> True stops between network calls
        (raises Cancelled): the batch is no longer wanted."""
        cfg, motor = self.cfg, self.motor
        Rt = tf.R.transpose(-1, -2)
        # the network sees the impulse in x0's velocities; the blending after it keeps the true x0
        x0_cond = x0c.clone()
        x0_cond[:, SLICES["velocities"]] += (batch.impulse_velocity @ Rt.transpose(-1, -2)).reshape(len(batch), 66)
        if cfg.steer_impulse > 0 or cfg.turn_impulse > 0:
            self._steer(x0_cond, batch.v_goal, batch.facing_goal, Rt)
        cond = motor.norm.encode(x0_cond.float())
        guide = self._guidance(batch.v_goal, batch.facing_goal, Rt.float(), x0c.float())
        N = motor.net.cfg.frames
        denoise = self._denoiser(batch, tf, cond)
        if cancelled is not None:
            inner = denoise

            def denoise(x_t, t):
                if cancelled():
                    raise Cancelled
                return inner(x_t, t)
        seg_n = motor.diffusion.sample(denoise, (len(batch), N, STATE_DIM), cfg.steps,
                                       batch.gens, guide, cfg.eta)
        return motor.norm.decode(seg_n).double()

    def _denoiser(self, batch: SegmentBatch, tf, cond):
        """The base network, or the adaptor with per-avatar controls (scale 0 for the avatars it does
        not steer, which is the base model exactly)."""
        net, ad = self.net, self.adaptor
        if ad is None or not any(batch.adapted):
            return lambda x_t, t: net(t, x_t, cond)
        scale = torch.tensor([s if on else 0.0 for on, s in zip(batch.adapted, batch.control_scales)])
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
        return lambda x_t, t: ad(t, x_t, cond, y, scale=s)

    def _steer(self, x0c: torch.Tensor, v_goals: list, f_goals: list, Rt: torch.Tensor) -> None:
        """Steering as an impulse (our addition): the network starts each segment already moving the
        way it should go. The body's initial velocity is moved toward the goal velocity
        (horizontally, by steer_impulse x the difference), and the body gets a yaw rate toward the
        facing goal (turn_impulse x the angle, rad/s), as velocities about the pelvis."""
        cfg = self.cfg
        vel = x0c[:, SLICES["velocities"]].view(len(x0c), 22, 3)
        J = x0c[:, SLICES["joints"]].view(len(x0c), 22, 3)
        for k, (v, f) in enumerate(zip(v_goals, f_goals)):
            angle = None
            if f is not None:
                goal_f = Rt[k] @ f.double()
                z, _ = facing_of(x0c[k])
                angle = torch.atan2(z[2] * goal_f[0] - z[0] * goal_f[2], (z * goal_f).sum())  # about +Y, z -> goal
            if v is not None and cfg.steer_impulse > 0:
                goal = Rt[k] @ v.double()
                if angle is not None and cfg.steer_with_body > 0:
                    goal = rot.yaw_matrix(-cfg.steer_with_body * angle) @ goal  # back toward where the body faces
                dv = cfg.steer_impulse * (goal - vel[k, STEER_JOINTS].mean(0))
                dv[1] = 0.0
                vel[k, STEER_JOINTS] += dv
            if angle is not None and cfg.turn_impulse > 0:
                w = cfg.turn_impulse * angle  # a signal to the network more than a physical rate
                r = J[k] - J[k, 0]
                vel[k] += torch.stack((w * r[:, 2], torch.zeros_like(w * r[:, 0]), -w * r[:, 0]), -1)

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
