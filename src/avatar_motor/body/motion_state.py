"""The 267-d motion state of PRIMAL §3.2 and its canonical frame.

One frame x = (r, phi, theta, J, Jdot):
    r      root (pelvis) translation, metres                       [0:3]
    phi    root global rotation, continuous 6D                     [3:9]
    theta  21 joint rotations relative to their parents, 6D        [9:135]
    J      22 joint locations, metres                              [135:201]
    Jdot   22 joint velocities, metres per SECOND, backward        [201:267]
           differences: Jdot_i = (J_i - J_{i-1}) * fps, so a state carries the momentum with which
           the body arrived at it (an impulse adds to it).

Canonical frame (after GAMMA, PRIMAL §3.2): origin at the pelvis of the segment's first frame
projected to the ground (y = 0, so the height above the ground stays visible to the model),
X left, Y up, Z forward, the facing taken from the hips' left-right axis.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import torch

from . import rotations as rot
from .skeleton import JOINT_INDEX, NUM_JOINTS, forward_kinematics

STATE_DIM = 267
FPS = 30.0
SLICES = {
    "root_pos": slice(0, 3),
    "root_rot": slice(3, 9),
    "local_rot": slice(9, 135),
    "joints": slice(135, 201),
    "velocities": slice(201, 267),
}
ROTATIONS = slice(SLICES["root_rot"].start, SLICES["local_rot"].stop)  # the 22 rotations' 6D channels, contiguous
_LH, _RH = JOINT_INDEX["left_hip"], JOINT_INDEX["right_hip"]


class Unpacked:
    """The parts of states (..., 267): root_pos (..., 3), root_rot (..., 3, 3), local_rot
    (..., 21, 3, 3), joints (..., 22, 3), velocities (..., 22, 3). The rotation matrices are made
    from their 6D channels when first read: a caller that needs only locations pays for no
    Gram-Schmidt (post-processing unpacks every segment several times)."""

    def __init__(self, x: torch.Tensor):
        lead = x.shape[:-1]
        self.state = x
        self.root_pos = x[..., SLICES["root_pos"]]
        self.joints = x[..., SLICES["joints"]].reshape(*lead, NUM_JOINTS, 3)
        self.velocities = x[..., SLICES["velocities"]].reshape(*lead, NUM_JOINTS, 3)

    @cached_property
    def rotations(self) -> torch.Tensor:
        """(..., 22, 3, 3): the root's global rotation and the 21 local ones, made in one call (their
        6D channels are contiguous): at one avatar each call's dispatch costs more than its work."""
        return rot.sixd_to_matrix(self.state[..., ROTATIONS].reshape(*self.state.shape[:-1], NUM_JOINTS, 6))

    @cached_property
    def root_rot(self) -> torch.Tensor:
        if "rotations" in self.__dict__:
            return self.rotations[..., 0, :, :]
        return rot.sixd_to_matrix(self.state[..., SLICES["root_rot"]])

    @cached_property
    def local_rot(self) -> torch.Tensor:
        return self.rotations[..., 1:, :, :]


def pack(root_pos, root_rot, local_rot, joints, velocities) -> torch.Tensor:
    """Matrices in, (..., 267) out."""
    lead = root_pos.shape[:-1]
    return torch.cat(
        (
            root_pos,
            rot.matrix_to_6d(root_rot),
            rot.matrix_to_6d(local_rot).reshape(*lead, 126),
            joints.reshape(*lead, 66),
            velocities.reshape(*lead, 66),
        ),
        -1,
    )


def unpack(x: torch.Tensor) -> Unpacked:
    if x.shape[-1] != STATE_DIM:
        raise ValueError(f"motion state must have {STATE_DIM} values per frame, got {x.shape[-1]}")
    return Unpacked(x)


def joints_of(x: torch.Tensor) -> torch.Tensor:
    return x[..., SLICES["joints"]].reshape(*x.shape[:-1], NUM_JOINTS, 3)


def velocities_of(x: torch.Tensor) -> torch.Tensor:
    return x[..., SLICES["velocities"]].reshape(*x.shape[:-1], NUM_JOINTS, 3)


def finite_velocities(joints: torch.Tensor, fps: float = FPS, first: torch.Tensor | None = None) -> torch.Tensor:
    """Backward differences along the frame axis (-3) of joints (..., T, 22, 3), per second.

    `first` is the velocity for frame 0 (e.g. the state's own velocity); by default frame 0 repeats
    frame 1's velocity."""
    v = (joints[..., 1:, :, :] - joints[..., :-1, :, :]) * fps
    if first is not None:
        v0 = first[..., None, :, :]
    elif joints.shape[-3] > 1:
        v0 = v[..., :1, :, :]
    else:  # a single frame: nothing to difference
        v0 = torch.zeros_like(joints)
    return torch.cat((v0, v), -3)


def states_from_motion(root_pos, root_rot, local_rot, offsets, fps: float = FPS) -> torch.Tensor:
    """Full states (..., T, 267) of a motion via the one FK; velocities by backward differences
    (frame 0 uses forward difference, as nothing precedes it)."""
    joints, _ = forward_kinematics(root_pos, root_rot, local_rot, offsets[..., None, :, :] if offsets.dim() > 2 else offsets)
    vel = finite_velocities(joints, fps)
    return pack(root_pos, root_rot, local_rot, joints, vel)


def body_joints(x: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    """The body a user takes away: FK of the root and joint rotations of states (..., 267) on the
    bone offsets (..., 22, 3) of their shape. Exporters write these rotations; the runtime makes
    the joint locations of every state it emits equal to this (`body_mismatch` measures it)."""
    u = unpack(x)
    return forward_kinematics(u.root_pos, u.root_rot, u.local_rot, offsets)[0]


def body_mismatch(x: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    """Per joint, the distance (m) between the joint locations a state carries and body_joints:
    (..., 22). Zero for a state that describes one body."""
    return (joints_of(x) - body_joints(x, offsets)).norm(dim=-1)


_HORIZONTAL = torch.tensor([1.0, 0.0, 1.0])


def horizontal(v: torch.Tensor) -> torch.Tensor:
    """v (..., 3) in the ground plane: its vertical (y) component zeroed."""
    return v * _HORIZONTAL.to(v.dtype)


def facing_yaw(joints: torch.Tensor) -> torch.Tensor:
    """Yaw angle (radians, about +Y, 0 = facing +Z) of the body from its hips' left-right axis."""
    left = joints[..., _LH, :] - joints[..., _RH, :]
    # forward = left x up = (-left_z, 0, left_x) for up = +Y
    return torch.atan2(-left[..., 2], left[..., 0])  # R_Y(yaw) @ (0, 0, 1) = forward


@dataclass
class Transform:
    """World <- canonical: x_world = R @ x_canon + t (R a yaw rotation)."""
    R: torch.Tensor  # (..., 3, 3)
    t: torch.Tensor  # (..., 3)


def canonical_transform(x0: torch.Tensor) -> Transform:
    """The canonical frame of a segment from its first state x0 (..., 267)."""
    J = joints_of(x0)
    yaw = facing_yaw(J)
    t = J[..., 0, :].clone()
    t[..., 1] = 0.0
    return Transform(rot.yaw_matrix(yaw), t)


def apply_transform(x: torch.Tensor, R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """x' = R x + t applied to every spatial part of states (..., T, 267); R, t have shape (..., 3, 3), (..., 3).
    The root rotation's 6D channels are its first two columns, so they are rotated as vectors:
    R @ Gram-Schmidt(a, b) = Gram-Schmidt(R a, R b) for a rotation R, in a few tensor ops (this
    runs three times per segment)."""
    lead = x.shape[:-1]
    # (..., T, 47, 3): the root location, the root rotation's two columns, the joint locations
    # and velocities, as 3-vectors; rows 0 and 3..24 are points, moved by the translation too
    V = torch.cat((x[..., :9], x[..., SLICES["joints"].start:]), -1).reshape(*lead, 47, 3)
    V = V @ R[..., None, :, :].transpose(-1, -2)
    t = t[..., None, None, :]
    V = torch.cat((V[..., :1, :] + t, V[..., 1:3, :], V[..., 3:25, :] + t, V[..., 25:, :]), -2).reshape(*lead, 141)
    return torch.cat((V[..., :9], x[..., 9:SLICES["joints"].start], V[..., 9:]), -1)


def canonicalize(states: torch.Tensor) -> tuple[torch.Tensor, Transform]:
    """states (..., T, 267) in world -> (canonical states, transform); frame 0 defines the frame."""
    tf = canonical_transform(states[..., 0, :])
    Rt = tf.R.transpose(-1, -2)
    return apply_transform(states, Rt, -(Rt @ tf.t[..., None])[..., 0]), tf


def to_world(states_c: torch.Tensor, tf: Transform) -> torch.Tensor:
    """Exact inverse of canonicalize."""
    return apply_transform(states_c, tf.R, tf.t)
