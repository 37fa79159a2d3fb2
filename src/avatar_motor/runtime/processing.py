"""Test-time processing. PRIMAL supplementary §8.2.2: snapping to the ground and inertialization
blending with Holden's decaying springs (Spring-It-On); PRIMAL's joint re-projection is what
`solve_body` makes of every frame (the one body: FK of the rotations, legs by two-bone IK). Ours,
each measured against the shipped model (see runtime/stages.py): velocity fusion, root adjustment
toward a facing goal, foot locking (with yaw for steered bodies), trend-keeping (and
speed-adaptive) smoothing, velocity-matched blending."""
from __future__ import annotations

import functools
import math

import torch

from ..body import rotations as rot
from ..body.skeleton import FOOT_CLEARANCE, JOINT_INDEX, JOINT_NAMES, PARENTS, forward_kinematics
from ..body.motion_state import FPS, ROTATIONS, SLICES, facing_yaw, horizontal, joints_of, pack, unpack


def _backward_velocities(x0: torch.Tensor, joints: torch.Tensor) -> torch.Tensor:
    """Velocities (B, N, 22, 3) of joint locations (B, N, 22, 3): backward differences, the first
    taken from the initial state x0 (B, 267)."""
    return (joints - torch.cat((joints_of(x0)[:, None], joints[:, :-1]), 1)) * FPS


def _pack_moving(x0: torch.Tensor, root_pos, root_rot, local_rot, joints: torch.Tensor) -> torch.Tensor:
    """Pack a segment (B, N, ...) whose velocities are the backward differences of its joints,
    the first one taken from the initial state x0 (B, 267)."""
    return pack(root_pos, root_rot, local_rot, joints, _backward_velocities(x0, joints))


def _moved(x0: torch.Tensor, seg: torch.Tensor, root_pos: torch.Tensor, joints: torch.Tensor,
           root_6d: torch.Tensor | None = None) -> torch.Tensor:
    """seg (B, N, 267) with new root positions and joint locations (and root rotation, 6D), its
    local rotations' channels kept as they are (no round trip through matrices), velocities the
    backward differences of the new locations, the first from x0."""
    B, N, _ = seg.shape
    parts = [root_pos, root_6d if root_6d is not None else seg[..., SLICES["root_rot"]],
             seg[..., SLICES["local_rot"]], joints.reshape(B, N, 66), _backward_velocities(x0, joints).reshape(B, N, 66)]
    return torch.cat(parts, -1)


def _move_frames(x0: torch.Tensor, u, R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Move each frame of an unpacked segment rigidly, p -> R p + t with R (B, N, 3, 3) and
    t (B, N, 3); local rotations are kept and velocities recomputed. The root's 6D channels (two
    columns of its rotation) are turned as the vectors they are: no Gram-Schmidt, which commutes
    with a rotation anyway."""
    B, N = t.shape[:2]
    Rt = R.transpose(-1, -2)
    joints = u.joints @ Rt + t[:, :, None]  # (a matmul: einsum took ~0.1 ms here at one avatar)
    root_pos = (u.root_pos[..., None, :] @ Rt)[..., 0, :] + t
    root_6d = (u.state[..., SLICES["root_rot"]].reshape(B, N, 2, 3) @ Rt).reshape(B, N, 6)
    return _moved(x0, u.state, root_pos, joints, root_6d)


_LEGS = [tuple(JOINT_INDEX[f"{side}_{j}"] for j in ("hip", "knee", "ankle", "foot")) for side in ("left", "right")]
assert not set(PARENTS) & {leg[3] for leg in _LEGS}  # solve_body places the feet as leaves


def two_bone_ik(a: torch.Tensor, b: torch.Tensor, c: torch.Tensor, target: torch.Tensor,
                bend_axis: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rotations that put the end c of the chain a-b-c (hip, knee, ankle positions (..., 3)) on
    `target`, bone lengths kept: the knee first opens or closes about the normal of the chain's
    plane to the distance |target - a| (clamped to what the bones reach), then the whole chain
    turns about a by the smallest rotation onto the target, so the knee stays in its plane.
    bend_axis (..., 3) is the knee's hinge for a straight leg, whose plane is undefined: the
    axis about which a positive turn bends the knee (closes its angle). Returns the world
    rotations (..., 3, 3) to apply at b (before) and at a (after): G_b' = R_a R_b G_b,
    G_a' = R_a G_a."""
    lab, lcb = (b - a).norm(dim=-1), (c - b).norm(dim=-1)
    lat = (target - a).norm(dim=-1).clamp(min=(lab - lcb).abs() + 1e-4, max=lab + lcb - 1e-4)
    cos_now = (rot.normalize(a - b) * rot.normalize(c - b)).sum(-1).clamp(-1.0, 1.0)
    cos_want = ((lab**2 + lcb**2 - lat**2) / (2 * lab * lcb)).clamp(-1.0, 1.0)
    # the plane's normal, oriented so that a positive turn bends the knee further; the hinge
    # takes over continuously as the leg straightens
    n = rot.normalize(torch.cross(b - a, c - b, dim=-1) + 1e-3 * bend_axis)
    R_b = rot.axis_angle_to_matrix(n * (torch.acos(cos_now) - torch.acos(cos_want))[..., None])
    c_new = b + (R_b @ (c - b)[..., None])[..., 0]
    R_a = rot.turn_onto(c_new - a, target - a)
    return R_a, R_b


def _above_ground(d: torch.Tensor, start: torch.Tensor, bone: torch.Tensor) -> torch.Tensor:
    """Direction d (..., 3), tilted up where needed so that a bone of the length of `bone` laid
    from `start` along it ends on or above the ground; its heading is kept (or the bone's own,
    for a d that points straight down)."""
    d = rot.normalize(d)
    lowest = (-start[..., 1] / bone.norm(dim=-1).clamp_min(1e-6)).clamp(-1.0, 1.0)  # smallest y of the unit direction
    flat = horizontal(d)
    flat = torch.where(flat.norm(dim=-1, keepdim=True) > 1e-6, flat, horizontal(bone))
    flat = rot.normalize(flat) * (1 - lowest**2).clamp_min(0).sqrt()[..., None]
    lifted = flat + lowest[..., None] * torch.tensor([0.0, 1.0, 0.0], dtype=d.dtype)
    return torch.where((d[..., 1] < lowest)[..., None], lifted, d)


def _pinned(start: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
    """Foot and ankle goals (B, N, 2, 3) moved horizontally, frame by frame, toward where the
    foot stood in the frame before (start (B, 3) before the first) by how planted the foot is
    (`_planted`, on the goals themselves): the ankle moves with its foot.
    The recurrence held_t = goal_t + w_t (held_{t-1} - goal_t) is unrolled into one weighted sum:
    held_t = sum_k (1 - w_k) prod_{k<i<=t} w_i goal_k + prod_{i<=t} w_i start."""
    B, N = goal.shape[:2]
    P = torch.cat((start[:, None], goal[:, :, 0]), 1)  # (B, N + 1, 3)
    w = _planted(P)  # (B, N)
    w0 = torch.cat((torch.ones_like(w[:, :1]), w), 1)  # (B, N + 1): frame 0 is the start, held as is
    later = torch.arange(N + 1)[:, None] > torch.arange(N + 1)[None, :]  # t > k
    carry = torch.where(later, w0[:, :, None], torch.ones(1, dtype=w.dtype)).cumprod(1)  # prod_{k<i<=t} w_i
    keep = torch.cat((torch.ones_like(w[:, :1]), 1 - w), 1)  # what of point k stays: all of the start
    M = torch.tril(carry * keep[:, None, :])  # (B, N + 1, N + 1), rows sum to 1
    held = (M @ P)[:, 1:]  # (B, N, 3)
    shift = horizontal(held - goal[:, :, 0])
    return goal + shift[:, :, None]


def solve_body(x0: torch.Tensor, seg: torch.Tensor, offsets: torch.Tensor,
               follow: float | torch.Tensor | None = None, pin: bool = False) -> torch.Tensor:
    """One body (DESIGN §5): the segment (B, N, 267) re-expressed as FK of its rotations on the
    body's own bones (offsets (B, 22, 3)), so the joint locations it carries are exactly those of
    the rotations exporters write. The pelvis location is the root; the rotations pose the body.
    With `follow` (0..1, a number or one per body (B,)) each leg is then bent by two-bone IK so
    that its ankle and foot move that fraction of the way to their processed locations (1: the
    processed feet exactly; 0: the rotations' feet), and nowhere below the ground; then any frame
    whose lowest joint is below the ground is lifted onto it. None: no IK, no lift.
    With `pin`, a planted foot (foot_contacts of those goals) is also held where it stood in the
    frame before (x0's for the first), as far as it is planted, so it does not slide whichever
    way the rotations move it. Velocities are the backward differences of the new locations, the
    first taken from x0."""
    u = unpack(seg)
    off = offsets.to(seg.dtype)[:, None]  # (B, 1, 22, 3)
    root = u.joints[:, :, 0]
    local = u.local_rot
    if follow is not None:  # both legs at once: index (B, N, leg, ...)
        hip, knee, ankle, foot = (list(j) for j in zip(*_LEGS))
        P, G = forward_kinematics(root, u.root_rot, u.local_rot, off)  # G: (B, N, 22, 3, 3) global rotations
        ends = torch.tensor([foot, ankle]).T  # (leg, foot/ankle)
        follow = torch.as_tensor(follow, dtype=seg.dtype).expand(seg.shape[0])[:, None, None, None, None]
        goal = P[:, :, ends] + follow * (u.joints[:, :, ends] - P[:, :, ends])  # (B, N, 2, 2, 3)
        if pin:
            B, N = goal.shape[:2]
            start = joints_of(x0)[:, foot].reshape(B * 2, 3)
            goal = _pinned(start, goal.transpose(1, 2).reshape(B * 2, N, 2, 3)).reshape(B, 2, N, 2, 3).transpose(1, 2)
        goal[..., 1] = torch.maximum(goal[..., 1], torch.tensor([0.0, FOOT_CLEARANCE], dtype=seg.dtype))  # foot, ankle
        G_hip, G_knee, G_ankle = G[:, :, hip], G[:, :, knee], G[:, :, ankle]
        R_a, R_b = two_bone_ik(P[:, :, hip], P[:, :, knee], P[:, :, ankle], goal[..., 1, :],
                               G_knee[..., :, 0])  # the knee's hinge: its own left axis (X)
        ankle_local = G_knee.transpose(-1, -2) @ G_ankle
        G_hip, G_knee = R_a @ G_hip, R_a @ R_b @ G_knee
        G_ankle = G_knee @ ankle_local
        p_knee = P[:, :, hip] + (G_hip @ off[:, :, knee, :, None])[..., 0]
        p_ankle = p_knee + (G_knee @ off[:, :, ankle, :, None])[..., 0]
        bone = (G_ankle @ off[:, :, foot, :, None])[..., 0]
        G_ankle = rot.turn_onto(bone, _above_ground(goal[..., 0, :] - p_ankle, p_ankle, bone)) @ G_ankle
        # the foot joints keep their local rotations (index_copy rather than an indexed assignment,
        # whose trace would keep the batch size: runtime/stage_graph.py)
        local = local.index_copy(2, torch.tensor([j - 1 for j in hip + knee + ankle]), torch.cat(
            (G[:, :, [PARENTS[j] for j in hip]].transpose(-1, -2) @ G_hip, G_hip.transpose(-1, -2) @ G_knee,
             G_knee.transpose(-1, -2) @ G_ankle), 2))
        # FK of the new rotations: only the legs below the hips moved (the feet are leaves)
        J = P.index_copy(2, torch.tensor(knee + ankle + foot),
                         torch.cat((p_knee, p_ankle, p_ankle + (G_ankle @ off[:, :, foot, :, None])[..., 0]), 2))
    else:
        J, _ = forward_kinematics(root, u.root_rot, local, off)
    if follow is not None:
        # the rest of the body above the ground too: a rolling or falling body rests on its back or
        # head, it does not sink (the legs are above it already); lifted per frame, pose unchanged
        lift = (-J[..., 1].amin(-1)).clamp(min=0.0)  # (B, N)
        up = torch.stack((torch.zeros_like(lift), lift, torch.zeros_like(lift)), -1)  # (B, N, 3)
        root, J = root + up, J + up[:, :, None]
    return _pack_moving(x0, root, u.root_rot, local, J)


@functools.lru_cache(maxsize=16)
def _fusion(N: int, weight: float, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """fuse_velocities' solution x = A^-1 (P + weight D^T b) as two fixed N x N matrices, A^-1 and
    weight A^-1 D^T, where D takes differences (x_t - x_{t-1}) and A = I + weight D^T D. (Made
    outside inference mode: kept, they may later meet tensors that autograd records.)"""
    with torch.inference_mode(False):
        D = torch.eye(N, dtype=torch.float64) - torch.diag(torch.ones(N - 1, dtype=torch.float64), -1)
        A_inv = torch.linalg.inv(torch.eye(N, dtype=torch.float64) + weight * D.T @ D)
        return A_inv.to(dtype), (weight * A_inv @ D.T).to(dtype)


def fuse_velocities(x0: torch.Tensor, seg: torch.Tensor, weight: float = 1.0) -> torch.Tensor:
    """Joint locations that agree with both of the network's estimates (our addition): the
    predicted locations P and the predicted velocities V, which are about twice as smooth as the
    differences of P. Per joint and axis, least squares over the segment's frames x_1..x_N with x0
    fixed: sum |x_t - P_t|^2 + weight sum |x_t - x_{t-1} - V_t / fps|^2. One N x N system shared
    by every channel. The root follows the pelvis; velocities are recomputed as differences."""
    if weight <= 0:
        return seg
    B, N, _ = seg.shape
    u0, u = unpack(x0), unpack(seg)
    to_P, to_V = _fusion(int(N), float(weight), seg.dtype)
    b = u.velocities.reshape(B, N, 66) / FPS
    b = torch.cat((b[:, :1] + u0.joints.reshape(B, 1, 66), b[:, 1:]), 1)  # the first difference is taken from x0
    joints = (to_P @ u.joints.reshape(B, N, 66) + to_V @ b).reshape(B, N, 22, 3)
    root_pos = u.root_pos + (joints[:, :, 0] - u.joints[:, :, 0])
    return _moved(x0, seg, root_pos, joints)


PAST = 8  # frames of an avatar's shown past the join reads (the widest smoothing kernel's radius)


def continuous_past(x0: torch.Tensor, past: torch.Tensor, has_past: torch.Tensor, tolerance: float = 1e-3) -> torch.Tensor:
    """(B,) bool: the frames past (B, P, 267) lead into x0 (B, 267): x0's joints minus its velocity
    (a backward difference) land on the last of them. A body moved between frames (a reset, a
    raised or stood-up body) has a past that is not its own."""
    if past.shape[1] == 0:
        return torch.zeros(len(x0), dtype=torch.bool)
    u0 = unpack(x0)
    before = u0.joints - u0.velocities / FPS
    gap = (joints_of(past[:, -1]) - before).norm(dim=-1).amax(-1)
    return has_past & (gap < tolerance)


def _history(x0: torch.Tensor, r: int) -> torch.Tensor:
    """r frames before the initial state x0 (B, 267), oldest first: positions extrapolated back
    along x0's joint velocities (the past continued at constant velocity), rotations held."""
    u = unpack(x0)
    k = torch.arange(r, 0, -1, dtype=x0.dtype)[None, :, None]  # r .. 1 frames back
    past = x0[:, None].repeat(1, r, 1)
    vel = u.velocities.reshape(x0.shape[0], 1, 66)
    past[..., SLICES["joints"]] = x0[:, None, SLICES["joints"]] - k * vel / FPS
    past[..., SLICES["root_pos"]] = x0[:, None, SLICES["root_pos"]] - k * vel[..., :3] / FPS  # root = pelvis
    return past


def smooth_segment(x0: torch.Tensor, seg: torch.Tensor, sigma: float | torch.Tensor = 1.0,
                   past: torch.Tensor | None = None, has_past: torch.Tensor | None = None,
                   max_sigma: float | None = None) -> torch.Tensor:
    """Temporal low-pass of a generated segment (our addition to PRIMAL's processing): a Gaussian
    of `sigma` frames (a number, or one per body (B,)) along time over root position, rotations (in
    6D, re-orthonormalized) and joint locations. In front of the segment stands x0's past: the
    frames shown before it (past (B, P, 267), oldest first, where has_past (B,) says they lead
    into x0), else x0 continued back at its velocity with its rotations held; the end is
    point-reflected. The network's x0 estimate keeps a little of the last step's noise; at 30 fps that is mm-scale jitter which reads
    as foot skating. Velocities are recomputed afterwards. max_sigma: a bound on sigma known
    before the data, which fixes the kernel's extent (what a traced graph needs; the result is the
    same: each body's kernel is cut at its own radius)."""
    B, _, D = seg.shape
    sig = torch.as_tensor(sigma, dtype=seg.dtype).expand(B)
    if max_sigma is None and float(sig.max()) <= 0:
        return seg
    # each body's kernel ends at its own 2.5 sigma, so a body in a crowd is smoothed as it is alone
    # (a still body's wider kernel widened everyone's: the padding's far frames weighed in)
    radius = torch.ceil(2.5 * sig).clamp_min(1)  # (B,)
    r = int(radius.max()) if max_sigma is None else max(1, math.ceil(2.5 * max_sigma))
    t = torch.arange(-r, r + 1, dtype=seg.dtype)
    k = torch.exp(-0.5 * (t / sig[:, None].clamp_min(1e-3)) ** 2)  # (B, 2r + 1); sigma 0 -> a delta
    k = k * (t.abs() <= radius[:, None])
    k = k / k.sum(1, keepdim=True)
    front = _history(x0, r - 1)
    if past is not None and r > 1:
        # the frames shown, rotations turning as they did (held ones braked every join: a jerk
        # twice every second); older ones extrapolated where P < r - 1
        known = past[:, -(r - 1):]
        known = torch.cat((front[:, :r - 1 - known.shape[1]], known), 1)
        front = torch.where(has_past[:, None, None], known.to(front.dtype), front)
    pad_front = torch.cat((front, x0[:, None]), 1) if r > 1 else x0[:, None]
    # the end point-reflected (2 x_N - x_{N-k}): continues the segment's trend, where a mirror
    # image would bring every segment to a halt at its last frame
    mirror = seg.flip(1)[:, 1:r + 1]
    if mirror.shape[1] < r:
        mirror = torch.cat((mirror, seg[:, :1].expand(B, r - mirror.shape[1], D)), 1)
    pad_back = 2 * seg[:, -1:] - mirror
    full = torch.cat((pad_front, seg, pad_back), 1)  # (B, N + 2r, D)
    out = (full.unfold(1, 2 * r + 1, 1) @ k[:, None, :, None])[..., 0]  # (B, N, D)
    u = unpack(out)
    # re-orthonormalize rotations through 6D -> matrix -> 6D (pack does it) and difference velocities
    return _pack_moving(x0, u.root_pos, u.root_rot, u.local_rot, u.joints)


def snap_to_ground(seg: torch.Tensor, ground: float = FOOT_CLEARANCE) -> torch.Tensor:
    """Translate each segment (B, N, 267) vertically so its lowest joint over all frames sits at
    `ground` (the height of a standing foot joint): over 0.5 s some joint touches the ground."""
    J = seg[..., SLICES["joints"]].reshape(*seg.shape[:-1], 22, 3)
    dy = ground - J[..., 1].amin((-1, -2))  # (B,)
    out = seg.clone()
    out[..., 1] += dy[:, None]
    out[..., SLICES["joints"].start + 1:SLICES["joints"].stop:3] += dy[:, None, None]
    return out


CONTACT_HEIGHT = (0.06, 0.10)  # a foot joint below the first is planted, above the second free (m)
CONTACT_SPEED = (0.5, 1.2)  # likewise for its horizontal speed (m/s)


def _ramp(x: torch.Tensor, lo: float, hi: float) -> torch.Tensor:
    return ((hi - x) / (hi - lo)).clamp(0.0, 1.0)


def _planted(P: torch.Tensor) -> torch.Tensor:
    """How planted a foot joint is in each frame of its positions P (B, N + 1, ..., 3), the first
    being the frame before: 1 when low and slow, ramping linearly to 0 between the bounds of
    CONTACT_HEIGHT (m above ground) and CONTACT_SPEED (m/s). Returns (B, N, ...)."""
    h, v = P[:, 1:, ..., 1], (P[:, 1:] - P[:, :-1])[..., [0, 2]].norm(dim=-1) * FPS
    return _ramp(h, *CONTACT_HEIGHT) * _ramp(v, *CONTACT_SPEED)


def foot_contacts(x0: torch.Tensor, seg: torch.Tensor) -> torch.Tensor:
    """How planted each foot is in each frame of seg (B, N, 267) after x0 (B, 267) (`_planted`).
    Returns the contacts (B, N, 2)."""
    feet = [JOINT_INDEX["left_foot"], JOINT_INDEX["right_foot"]]
    return _planted(torch.cat((joints_of(x0)[:, None], joints_of(seg)), 1)[:, :, feet])


def lock_feet(x0: torch.Tensor, seg: torch.Tensor, where: torch.Tensor | None = None,
              yaw: bool | torch.Tensor = False, turned: torch.Tensor | None = None) -> torch.Tensor:
    """Root motion from the feet (our addition, as game engines do): a foot that is low and slow is
    planted (foot_contacts), so whatever it slides horizontally is the body sliding. Frame by frame
    the whole body is moved back by the contact-weighted mean slide of the two feet, accumulated
    over the segment (x0 stays where it is). With `yaw` (a bool, or one per body (B,)), a body on
    two planted feet is also turned back about its pelvis by the yaw that the line between its feet
    turned (weighted by the weaker contact), so a body that twists in double support pivots instead
    of sliding both feet apart. The contact weights fade in and out, so the correction does not
    jolt. Bones and local rotations are untouched; velocities are recomputed. where (B,) bool
    limits the correction to some bodies; turned (B, N) is a yaw per frame that was added on
    purpose (turn_toward's) and is not undone."""
    B, N, _ = seg.shape
    u = unpack(seg)
    c = foot_contacts(x0, seg)  # (B, N, 2)
    if where is not None:
        c = c * where.to(c.dtype)[:, None, None]
    feet = [JOINT_INDEX["left_foot"], JOINT_INDEX["right_foot"]]
    P = torch.cat((unpack(x0).joints[:, None], u.joints), 1)[:, :, feet]  # (B, N + 1, 2, 3)
    a = (P[:, :, 0] - P[:, :, 1])[..., [0, 2]]  # the line between the feet, horizontal
    back = torch.atan2(a[:, 1:, 1] * a[:, :-1, 0] - a[:, 1:, 0] * a[:, :-1, 1], (a[:, 1:] * a[:, :-1]).sum(-1))
    if turned is not None:  # the line turned by that on purpose too
        back = back + torch.diff(turned.to(seg.dtype), dim=1, prepend=torch.zeros_like(turned[:, :1]))
    on = torch.as_tensor(yaw, dtype=seg.dtype).expand(B)[:, None]
    R = rot.yaw_matrix((back * c.amin(-1) * on).cumsum(1))  # (B, N, 3, 3): each frame's turn back
    pivot = horizontal(u.joints[:, :, 0])  # (B, N, 3)
    t = pivot - (R @ pivot[..., None])[..., 0]  # turn about the pelvis
    feet_now = P[:, 1:] @ R.transpose(-1, -2) + t[:, :, None]  # the feet after the turn back
    step = (feet_now - torch.cat((P[:, :1], feet_now[:, :-1]), 1))[..., [0, 2]]  # (B, N, 2, 2)
    d = -(c[..., None] * step).sum(2) / c.sum(2, keepdim=True).clamp(min=1.0)  # (B, N, 2)
    slide = d.cumsum(1)
    t = t + torch.stack((slide[..., 0], torch.zeros_like(slide[..., 0]), slide[..., 1]), -1)
    return _move_frames(x0, u, R, t)


def turn_toward(x0: torch.Tensor, seg: torch.Tensor, goal_yaw: torch.Tensor, max_rate: float,
                tolerance: float = 0.0, where: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Turn each body toward a facing goal (our addition; game engines call it root adjustment).
    The network turns slowly or side-steps where the data did; whatever facing error is left at
    the segment's last frame (hips, as L_facing measures it) is taken out by a yaw rotation that
    grows over the segment from 0 at x0 (so the join is continuous). It grows while at most one
    foot is planted, at most max_rate rad/s in any frame: turning a body in double support would
    slide both feet (a body planted on both feet all segment long turns evenly). Each frame turns
    about its own pelvis, so the path is kept and only the facing changes; foot locking afterwards
    makes a planted foot the pivot. The next segment is conditioned on the turned body, so the
    network walks the way it now faces. seg (B, N, 267) and goal_yaw (B,) in x0's frame;
    tolerance (rad): the error left alone (a walking pelvis swings a few degrees); where (B,) bool
    limits it to some bodies. Returns the turned segment and each frame's added yaw (B, N)."""
    u = unpack(seg)
    err = goal_yaw.to(seg.dtype) - facing_yaw(u.joints[:, -1])
    err = torch.atan2(torch.sin(err), torch.cos(err))  # wrapped to (-pi, pi]
    free = 1.0 - foot_contacts(x0, seg).amin(-1)  # (B, N): 0 in double support
    free = torch.where(free.sum(1, keepdim=True) > 0.5, free, torch.ones_like(free))
    limit = max_rate * free.sum(1) / FPS  # each frame turns at most max_rate / FPS
    total = torch.minimum(torch.maximum(err - err.clamp(-tolerance, tolerance), -limit), limit)  # errors within tolerance stay
    if where is not None:
        total = total * where.to(seg.dtype)
    yaw = total[:, None] * free.cumsum(1) / free.sum(1, keepdim=True)  # 0 -> total over the segment
    R = rot.yaw_matrix(yaw)  # (B, N, 3, 3)
    pivot = horizontal(u.joints[:, :, 0])  # (B, N, 3)
    return _move_frames(x0, u, R, pivot - (R @ pivot[..., None])[..., 0]), yaw


def _damping(halflife: float) -> float:
    return 4.0 * math.log(2.0) / max(halflife, 1e-5)


def spring_decay(x: torch.Tensor, v: torch.Tensor, halflife: float, t: torch.Tensor) -> torch.Tensor:
    """Critically damped decay of an offset x with velocity v after time t (broadcast on t)."""
    y = _damping(halflife) / 2.0
    j1 = v + x * y
    e = torch.exp(-y * t)
    return e * (x + j1 * t)


# the rotations whose turn at a join inertialize matches: spine, neck, head and arms, and for a
# body without a facing goal its root. Not the legs: with theirs matched too the joins were
# smoother still, but over a minute the avatars stopped stepping and stood; not the root of a
# body turning toward a facing goal: it then turned later (figures: the persona card, blending)
_TURN_MATCHED = torch.tensor([j != 0 and not any(k in name for k in ("hip", "knee", "ankle", "foot"))
                              for j, name in enumerate(JOINT_NAMES)])
_ROOT = torch.arange(22) == 0


def inertialize(x0: torch.Tensor, seg: torch.Tensor, halflife: float = 0.1,
                match_velocity: torch.Tensor | None = None, before: torch.Tensor | None = None,
                has_before: torch.Tensor | None = None, turn_root: torch.Tensor | None = None) -> torch.Tensor:
    """Blend the start of generated frames seg (B, N, 267) into the initial state x0 (B, 267).

    The new motion, extrapolated back one frame to the time of x0 (x1 - (x2 - x1)), should be x0;
    the difference is an offset that decays as a critically damped spring (Holden's
    inertialization) over the segment, for the root position, the joint locations and every
    rotation (in its 6D channels, which the stages after turn into a rotation by Gram-Schmidt).
    Where match_velocity (B,) is true the joint velocities are matched too (offset x0's velocity
    minus the new motion's first velocity), so the stream has no kink at the join. Where it is
    false (the avatar was just pushed: x0's velocity carries an impulse that the network has
    already turned into motion and must not be added again) only positions are blended. With
    the frame shown before x0 (before (B, 267), where has_before (B,)), the velocities of the
    upper body's rotations are matched as well (each one's turn from it to x0 against the new
    motion's first turn; _TURN_MATCHED), and the root's where turn_root (B,); other rotations are
    blended in position only.
    Velocities are then recomputed as backward differences, so the result is consistent.
    """
    B, N, _ = seg.shape
    dt = 1.0 / FPS
    t = (torch.arange(1, N + 1, dtype=seg.dtype) * dt)[None, :, None]
    u0, u = unpack(x0), unpack(seg)
    nxt = 1 if N > 1 else 0
    back = 2 * u.joints[:, 0] - u.joints[:, nxt]  # the segment extrapolated to x0's time
    off_J = (u0.joints - back).reshape(B, 1, 66)
    off_V = torch.zeros_like(off_J)
    if match_velocity is not None and N > 1:
        v_new = (u.joints[:, nxt] - u.joints[:, 0]) * FPS
        off_V = torch.where(match_velocity.reshape(B, 1, 1), (u0.velocities - v_new).reshape(B, 1, 66), off_V)
    dJ = spring_decay(off_J, off_V, halflife, t).reshape(B, N, 22, 3)
    joints = u.joints + dJ
    root_pos = u.root_pos + dJ[:, :, 0]  # the root is the pelvis
    # rotations in their 6D channels (two columns of each matrix), blended linearly there: to first
    # order the geodesic blend of rotation vectors, in some 140 fewer tensor operations (the EMDM
    # card has what it changed). Only an offset near half a turn would pass through a degenerate
    # frame; the shipped model's joins are within a few degrees, after a preset at most ~130
    S0 = x0[:, ROTATIONS].reshape(B, 22, 6)
    S = seg[..., ROTATIONS].reshape(B, N, 22, 6)
    S_back = 2 * S[:, 0] - S[:, nxt]  # extrapolated back one frame
    off_r = S0 - S_back
    off_w = torch.zeros_like(off_r)
    if before is not None and match_velocity is not None and N > 1:
        # the per frame turns: x0's from the frame before, the new motion's first
        turned = _TURN_MATCHED.reshape(1, 22, 1)
        if turn_root is not None:
            turned = turned | (turn_root.reshape(B, 1, 1) & _ROOT.reshape(1, 22, 1))
        use = (match_velocity & has_before).reshape(B, 1, 1) & turned
        off_w = torch.where(use, ((S0 - before[:, ROTATIONS].reshape(B, 22, 6)) - (S[:, 0] - S_back)) * FPS, off_w)
    S = S + spring_decay(off_r[:, None], off_w[:, None], halflife, t[..., None])
    return torch.cat((root_pos, S.reshape(B, N, 132), joints.reshape(B, N, 66),
                      _backward_velocities(x0, joints).reshape(B, N, 66)), -1)


# a body outside these is not a person whatever the model did: the guard resets it
PELVIS_HEIGHT = (-0.5, 3.0)  # m
MAX_SPEED = 15.0  # m/s of the pelvis, horizontally, over a segment (a sprint is ~10)
BONE_TOLERANCE = 0.05  # m between a bone's length and its rest length


def physical_faults(x0: torch.Tensor, seg: torch.Tensor, offsets: torch.Tensor,
                    floor: torch.Tensor | None = None) -> list[str | None]:
    """Why each segment (B, N, 267), continuing from x0 (B, 267), is not a physical body on its bones
    `offsets` (B, 22, 3), or None: a non-finite value, the pelvis out of PELVIS_HEIGHT (above the
    ground under it: floor (B, N) m, its height at each frame; None: the floor y = 0) or moving
    faster than MAX_SPEED, a bone off its rest length. A guard, not a metric: a broken checkpoint
    (scaled weights put a pelvis at 352 km) must not be streamed."""
    out: list[str | None] = []
    J = joints_of(seg)  # (B, N, 22, 3)
    if floor is not None:  # heights above the ground (a tilted one falls metres below y = 0)
        J = J.clone()
        J[..., 1] -= floor.to(J.dtype)[..., None]
    bones = (J[..., 1:, :] - J[..., PARENTS[1:], :]).norm(dim=-1)  # (B, N, 21)
    rest = offsets[:, None, 1:].norm(dim=-1)
    travel = (J[:, :, 0, [0, 2]] - joints_of(x0)[:, None, 0, [0, 2]]).norm(dim=-1)  # (B, N)
    allowed = MAX_SPEED * torch.arange(1, seg.shape[1] + 1, dtype=seg.dtype) / FPS
    ok = (torch.isfinite(seg).flatten(1).all(1) & (J[:, :, 0, 1].amin(1) >= PELVIS_HEIGHT[0])
          & (J[:, :, 0, 1].amax(1) <= PELVIS_HEIGHT[1]) & (travel <= allowed).all(1)
          & ((bones - rest).abs().flatten(1).amax(1) <= BONE_TOLERANCE))
    for k, fine in enumerate(ok.tolist()):
        if fine:  # the common case, decided for the whole batch at once
            out.append(None)
        elif not torch.isfinite(seg[k]).all():
            out.append("non-finite values")
        elif not (PELVIS_HEIGHT[0] <= float(J[k, :, 0, 1].min()) and float(J[k, :, 0, 1].max()) <= PELVIS_HEIGHT[1]):
            out.append(f"pelvis height {float(J[k, :, 0, 1].min()):.3g}..{float(J[k, :, 0, 1].max()):.3g} m "
                       f"outside {PELVIS_HEIGHT}")
        elif bool((travel[k] > allowed).any()):
            out.append(f"pelvis moved {float(travel[k].max()):.3g} m in {seg.shape[1]} frames (above {MAX_SPEED} m/s)")
        elif float((bones[k] - rest[k]).abs().max()) > BONE_TOLERANCE:
            out.append(f"a bone {float((bones[k] - rest[k]).abs().max()):.3g} m off its length")
        else:
            out.append(None)
    return out


def nearest_candidate(cands: torch.Tensor, targets: torch.Tensor, penalty: torch.Tensor | None = None) -> torch.Tensor:
    """Index (P,) of the candidate segment, of K (P, K, N, 267) each avatar's sampler drew, whose
    pelvis ends nearest that avatar's target (P, 2) on the ground (x, z), in the same frame as
    the segments: best-of-K sampling for a reaching avatar. Its end, not its nearest frame: the
    next segment starts there, and a body that passes the target is not at it. penalty (P, K) m:
    added to each candidate's distance (a NaN target: the penalty alone decides)."""
    end = joints_of(cands[:, :, -1])[..., 0, :][..., [0, 2]]  # (P, K, 2)
    d = (end - targets[:, None].to(end.dtype)).norm(dim=-1)
    d = torch.nan_to_num(d, nan=0.0)
    return (d if penalty is None else d + penalty.to(d.dtype)).argmin(1)
