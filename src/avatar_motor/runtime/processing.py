"""Test-time processing of PRIMAL supplementary §8.2.2: joint re-projection, snapping to the
ground, and inertialization blending with Holden's decaying springs (Spring-It-On)."""
from __future__ import annotations

import math

import torch

from ..body import rotations as rot
from ..body.skeleton import FOOT_CLEARANCE, forward_kinematics
from ..data.motion_state import FPS, SLICES, pack, unpack


def reproject(x0: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    """Replace the joint locations of states (B, 267) by the FK of their own rotations."""
    u = unpack(x0)
    J, _ = forward_kinematics(u.root_pos, u.root_rot, u.local_rot, offsets)
    out = x0.clone()
    out[..., SLICES["joints"]] = J.reshape(*x0.shape[:-1], 66)
    return out


def smooth_segment(x0: torch.Tensor, seg: torch.Tensor, sigma: float = 1.0) -> torch.Tensor:
    """Temporal low-pass of a generated segment (our addition to PRIMAL's processing): a Gaussian
    of `sigma` frames along time over root position, rotations (in 6D, re-orthonormalized) and joint
    locations, with the initial state x0 (B, 267) fixed in front so the join stays continuous and
    the end reflected. The network's x0 estimate keeps a little of the last step's noise; at 30 fps
    that is mm-scale jitter which reads as foot skating. Velocities are recomputed afterwards."""
    if sigma <= 0:
        return seg
    B, N, D = seg.shape
    r = max(1, int(math.ceil(2.5 * sigma)))
    k = torch.exp(-0.5 * (torch.arange(-r, r + 1, dtype=seg.dtype) / sigma) ** 2)
    k = k / k.sum()
    # x0 repeated in front (the past is held), the end reflected
    pad_front = x0[:, None].expand(B, r, D)
    pad_back = seg.flip(1)[:, 1:r + 1]
    if pad_back.shape[1] < r:
        pad_back = torch.cat((pad_back, seg[:, -1:].expand(B, r - pad_back.shape[1], D)), 1)
    full = torch.cat((pad_front, seg, pad_back), 1)  # (B, N + 2r, D)
    out = torch.nn.functional.conv1d(full.transpose(1, 2).reshape(B * D, 1, -1), k.view(1, 1, -1)).reshape(B, D, N).transpose(1, 2)
    u = unpack(out)
    prev = torch.cat((x0[:, None], out[:, :-1]), 1)
    J_prev = prev[..., SLICES["joints"]].reshape(B, N, 22, 3)
    # re-orthonormalize rotations through 6D -> matrix -> 6D (pack does it) and difference velocities
    return pack(u.root_pos, u.root_rot, u.local_rot, u.joints, (u.joints - J_prev) * FPS)


def snap_to_ground(seg: torch.Tensor, ground: float = FOOT_CLEARANCE) -> torch.Tensor:
    """Translate each segment (B, N, 267) vertically so its lowest joint over all frames sits at
    `ground` (the height of a standing foot joint): over 0.5 s some joint touches the ground."""
    J = seg[..., SLICES["joints"]].reshape(*seg.shape[:-1], 22, 3)
    dy = ground - J[..., 1].amin((-1, -2))  # (B,)
    out = seg.clone()
    out[..., 1] += dy[:, None]
    out[..., SLICES["joints"].start + 1:SLICES["joints"].stop:3] += dy[:, None, None]
    return out


def _damping(halflife: float) -> float:
    return 4.0 * math.log(2.0) / max(halflife, 1e-5)


def spring_decay(x: torch.Tensor, v: torch.Tensor, halflife: float, t: torch.Tensor) -> torch.Tensor:
    """Critically damped decay of an offset x with velocity v after time t (broadcast on t)."""
    y = _damping(halflife) / 2.0
    j1 = v + x * y
    e = torch.exp(-y * t)
    return e * (x + j1 * t)


def inertialize(x0: torch.Tensor, seg: torch.Tensor, halflife: float = 0.1) -> torch.Tensor:
    """Blend the start of generated frames seg (B, N, 267) into the initial state x0 (B, 267).

    The new motion, extrapolated back one frame to the time of x0 (x1 - (x2 - x1)), should be x0;
    the difference is an offset that decays as a critically damped spring (Holden's
    inertialization) over the segment, for the root position, the joint locations and every
    rotation (as rotation vectors). The velocity offset is taken as zero: x0's velocity may carry
    an impulse, which the network has already turned into motion and must not be added again.
    Velocities are then recomputed as backward differences, so the result is consistent.
    """
    B, N, _ = seg.shape
    dt = 1.0 / FPS
    t = (torch.arange(1, N + 1, dtype=seg.dtype) * dt)[None, :, None]
    u0, u = unpack(x0), unpack(seg)
    nxt = 1 if N > 1 else 0
    back = 2 * u.joints[:, 0] - u.joints[:, nxt]  # the segment extrapolated to x0's time
    off_J = (u0.joints - back).reshape(B, 1, 66)
    dJ = spring_decay(off_J, torch.zeros_like(off_J), halflife, t).reshape(B, N, 22, 3)
    joints = u.joints + dJ
    root_pos = u.root_pos + dJ[:, :, 0]  # the root is the pelvis
    R0 = torch.cat((u0.root_rot[:, None], u0.local_rot), 1)  # (B, 22, 3, 3)
    R = torch.cat((u.root_rot[:, :, None], u.local_rot), 2)  # (B, N, 22, 3, 3)
    # rotation extrapolated back one frame: R1 (R2^T R1)
    R_back = R[:, 0] @ (R[:, nxt].transpose(-1, -2) @ R[:, 0])
    off_r = rot.matrix_to_axis_angle(R0 @ R_back.transpose(-1, -2))  # (B, 22, 3)
    d_r = spring_decay(off_r[:, None], torch.zeros_like(off_r[:, None]), halflife, t[..., None])
    R = rot.axis_angle_to_matrix(d_r) @ R
    prev = torch.cat((u0.joints[:, None], joints[:, :-1]), 1)
    vel = (joints - prev) * FPS
    return pack(root_pos, R[:, :, 0], R[:, :, 1:], joints, vel)
