"""Classifier-based guidance with analytic gradients (PRIMAL §3.4.2, supplementary §9.2).

Both losses act on the x0 estimate of a segment in its canonical frame, in real units:
    L_move   = || mean_{frames, joints} Jdot - v_goal ||^2                         (Eq. 7)
    L_facing = || z - r_goal ||^2, z the unit facing of the last frame from its hips (Eq. 8)
Their gradients are written out by hand (no autograd in the sampling loop); tests compare them
with autograd.
"""
from __future__ import annotations

import torch

from ..body.skeleton import JOINT_INDEX
from ..body.motion_state import SLICES, horizontal

_LH, _RH = JOINT_INDEX["left_hip"], JOINT_INDEX["right_hip"]
_J0 = SLICES["joints"].start
_V0 = SLICES["velocities"].start


def move_loss_and_grad(x: torch.Tensor, v_goal: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """x (B, N, 267) real units; v_goal (B, 3). Returns (loss (B,), dL/dx (B, N, 267))."""
    B, N, _ = x.shape
    vel = x[..., SLICES["velocities"]].reshape(B, N, 22, 3)
    diff = vel.mean((1, 2)) - v_goal  # (B, 3)
    grad = torch.zeros_like(x)
    g = (2.0 / (22 * N)) * diff  # d/d(each joint velocity)
    grad[..., SLICES["velocities"]] = g[:, None, None, :].expand(B, N, 22, 3).reshape(B, N, 66)
    return (diff**2).sum(-1), grad


def path_loss_and_grad(x: torch.Tensor, x0: torch.Tensor, v_goal: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Our addition to PRIMAL's L_move: the body's centroid (22 joints and the root translation)
    should travel from where it starts at v_goal, L_path = mean_i || c_i - (c_0 + v_goal i/fps) ||^2
    over the horizontal plane. Its gradient moves the whole body rigidly per frame (every point
    gets the same pull), so it steers without bending the pose; L_move alone acts on the velocity
    channels only, which a small model follows weakly.
    x (B, N, 267), x0 (B, 267) the initial state, v_goal (B, 3)."""
    from ..body.motion_state import FPS
    B, N, _ = x.shape

    def centroid(s):
        J = s[..., SLICES["joints"]].reshape(*s.shape[:-1], 22, 3)
        return (J.sum(-2) + s[..., SLICES["root_pos"]]) / 23.0

    c = centroid(x)
    t = centroid(x0)[:, None] + v_goal[:, None] * (torch.arange(1, N + 1, dtype=x.dtype) / FPS)[None, :, None]
    d = horizontal(c - t)
    loss = (d**2).sum(-1).mean(-1)
    g = 2 * d / (23.0 * N)  # (B, N, 3) per point
    grad = torch.zeros_like(x)
    grad[..., SLICES["root_pos"]] = g
    grad[..., SLICES["joints"]] = g.repeat(1, 1, 22)
    return loss, grad


def facing_of(x_last: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit horizontal facing (B, 3) of states (B, 267) and the unnormalized vector g = left x up."""
    J = x_last[..., SLICES["joints"]].reshape(*x_last.shape[:-1], 22, 3)
    left = J[..., _LH, :] - J[..., _RH, :]
    g = torch.stack((-left[..., 2], torch.zeros_like(left[..., 0]), left[..., 0]), -1)
    return g / g.norm(dim=-1, keepdim=True).clamp_min(1e-6), g


def facing_loss_and_grad(x: torch.Tensor, r_goal: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """x (B, N, 267); r_goal (B, 3) unit horizontal. Returns (loss (B,), dL/dx)."""
    z, g = facing_of(x[:, -1])
    d = z - r_goal
    loss = (d**2).sum(-1)
    n = g.norm(dim=-1, keepdim=True).clamp_min(1e-6)
    # dz/dg = (I - z z^T)/|g|  ->  dL/dg = (I - z z^T) 2 d / |g|
    dg = (2 * d - z * (z * 2 * d).sum(-1, keepdim=True)) / n
    # g = (-l_z, 0, l_x): dL/dl_x = dL/dg_z, dL/dl_z = -dL/dg_x
    dl = torch.stack((dg[:, 2], torch.zeros_like(dg[:, 0]), -dg[:, 0]), -1)
    grad = torch.zeros_like(x)
    grad[:, -1, _J0 + 3 * _LH:_J0 + 3 * _LH + 3] = dl
    grad[:, -1, _J0 + 3 * _RH:_J0 + 3 * _RH + 3] = -dl
    return loss, grad


# how fast a stick's path turns from the body's motion to the goal's (a critically damped
# approach, as motion-matching controllers predict it): half the difference is gone after this
# many seconds. It is the commanded path `eval persona` measures TPE from; the persona model is
# asked for a quicker one (RuntimeConfig.trajectory_halflife)
TRAJECTORY_HALFLIFE = 0.25


def goal_trajectory(x0: torch.Tensor, v_goal: torch.Tensor, f_goal: torch.Tensor | None, frames: int,
                    halflife: float = TRAJECTORY_HALFLIFE) -> torch.Tensor:
    """The persona model's trajectory condition (B, frames, 4) for a goal, in the canonical frame of
    initial states x0 (B, 267): the root leaves where it stands with the velocity it has and
    approaches v_goal (B, 3), its facing approaches f_goal (B, 3; None or a zero row: keeps its own), each
    exponentially with `halflife`. Columns: x, z, sin yaw, cos yaw (model/persona.trajectory_of)."""
    from ..body.motion_state import FPS
    from ..model.persona import trajectory_of
    if not halflife > 0:
        raise ValueError(f"the trajectory's half-life must be above 0 s, got {halflife!r} (runtime trajectory_halflife)")
    B = len(x0)
    lam = 0.6931471805599453 / halflife
    t = torch.arange(1, frames + 1, dtype=x0.dtype) / FPS  # (F,)
    decay = torch.exp(-lam * t)
    start = trajectory_of(x0[:, None])[:, 0]  # (B, 4)
    v0 = x0[..., SLICES["velocities"]].reshape(B, 22, 3)[:, 0, [0, 2]]  # the pelvis, m/s
    vg = v_goal[:, [0, 2]].to(x0.dtype)
    # integral of vg + (v0 - vg) e^{-lam s} from 0 to t
    pos = start[:, None, :2] + vg[:, None] * t[None, :, None] + ((v0 - vg) / lam)[:, None] * (1 - decay)[None, :, None]
    yaw0 = torch.atan2(start[:, 2], start[:, 3])
    if f_goal is None:
        yaw = yaw0[:, None].expand(B, frames)
    else:
        f = f_goal.to(x0.dtype)
        yg = torch.where(f[:, [0, 2]].norm(dim=-1) > 1e-6, torch.atan2(f[:, 0], f[:, 2]), yaw0)
        d = torch.remainder(yaw0 - yg + torch.pi, 2 * torch.pi) - torch.pi  # the short way round
        yaw = yg[:, None] + d[:, None] * decay[None]
    return torch.cat((pos, torch.sin(yaw)[..., None], torch.cos(yaw)[..., None]), -1)
