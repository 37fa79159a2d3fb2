"""The one rotation library: 6D <-> matrix <-> quaternion <-> axis-angle <-> Euler angles.

Conventions (used everywhere in the project):
- Rotation matrices act on column vectors: v_world = R @ v_local.
- Quaternions are (w, x, y, z), unit norm; `matrix_to_quat` returns w >= 0.
- The continuous 6D representation (Zhou et al. 2019) is the first two *columns* of R,
  flattened as (R00, R10, R20, R01, R11, R21).
- Euler orders are strings of three axes like "ZXY" as written in a BVH CHANNELS line: the
  rotation is R = R_Z(a0) @ R_X(a1) @ R_Y(a2) (intrinsic, first-listed applied outermost), which
  is what every BVH reader does. Angles in radians here; BVH degrees are converted in io/.
All functions take any leading batch shape and work in float32 or float64.
"""
from __future__ import annotations

import torch

_AXES = {"X": 0, "Y": 1, "Z": 2}


def normalize(v: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    # linalg's norm directly: Tensor.norm goes through a Python wrapper, and this runs ~100 times per segment
    return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True).clamp_min(eps)


# ---------------------------------------------------------------- 6D
def matrix_to_6d(R: torch.Tensor) -> torch.Tensor:
    return R[..., :, :2].transpose(-1, -2).reshape(*R.shape[:-2], 6)


def sixd_to_matrix(d6: torch.Tensor) -> torch.Tensor:
    """Gram-Schmidt on the two stored columns; exact inverse of matrix_to_6d for rotations."""
    a1, a2 = d6[..., :3], d6[..., 3:]
    b1 = normalize(a1)
    b2 = normalize(a2 - (b1 * a2).sum(-1, keepdim=True) * b1)
    b3 = torch.cross(b1, b2, dim=-1)
    return torch.stack((b1, b2, b3), dim=-1)


# ---------------------------------------------------------------- axis-angle
def _cross_map() -> torch.Tensor:
    """(3, 9): v @ it is [v]x flattened row by row, (0, -z, y, z, 0, -x, -y, x, 0)."""
    C = torch.zeros(3, 9, dtype=torch.float64)
    for i, j, k, sign in ((0, 1, 2, -1), (0, 2, 1, 1), (1, 0, 2, 1), (1, 2, 0, -1), (2, 0, 1, -1), (2, 1, 0, 1)):
        C[k, 3 * i + j] = sign  # K[i, j] = sign * v[k]
    return C


_CROSS = _cross_map()


def skew(v: torch.Tensor) -> torch.Tensor:
    """[v]x (..., 3, 3), the matrix of v x ., as one product (not nine picked entries)."""
    return (v @ _CROSS.to(v.dtype)).reshape(*v.shape[:-1], 3, 3)


def axis_angle_to_matrix(aa: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula on the unnormalised axis K = [aa]x: R = I + sin(t)/t K + (1 - cos(t))/t^2 K^2,
    the two factors taken from their Taylor series near t = 0, where they are exact to the
    precision and keep gradients finite."""
    theta = torch.linalg.vector_norm(aa, dim=-1, keepdim=True)
    small = theta < 1e-4
    th = torch.where(small, torch.ones_like(theta), theta)  # no 0/0 in the branch not taken
    t2 = theta * theta
    a = torch.where(small, 1 - t2 / 6, torch.sin(th) / th)[..., None]
    b = torch.where(small, 0.5 - t2 / 24, (1 - torch.cos(th)) / (th * th))[..., None]
    K = skew(aa)
    return torch.eye(3, dtype=aa.dtype, device=aa.device) + a * K + b * (K @ K)


def quat_to_axis_angle(q: torch.Tensor) -> torch.Tensor:
    q = normalize(q)
    q = torch.where(q[..., :1] < 0, -q, q)
    v = q[..., 1:]
    s = v.norm(dim=-1, keepdim=True)
    angle = 2 * torch.atan2(s, q[..., :1])
    scale = torch.where(s < 1e-8, 2.0 / q[..., :1].clamp_min(1e-8), angle / s.clamp_min(1e-12))
    return v * scale


def axis_angle_to_quat(aa: torch.Tensor) -> torch.Tensor:
    theta = aa.norm(dim=-1, keepdim=True)
    half = theta / 2
    k = torch.where(theta < 1e-8, 0.5 - theta**2 / 48, torch.sin(half) / theta.clamp_min(1e-12))
    return torch.cat((torch.cos(half), aa * k), -1)


def matrix_to_axis_angle(R: torch.Tensor) -> torch.Tensor:
    return quat_to_axis_angle(matrix_to_quat(R))


# ---------------------------------------------------------------- quaternions
def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    q = normalize(q)
    w, x, y, z = q.unbind(-1)
    R = torch.stack(
        (
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ),
        -1,
    )
    return R.reshape(*q.shape[:-1], 3, 3)


# Shepperd's four candidate quaternions (4 x 4, rows) and the diagonal terms that choose among
# them (trace, R00, R11, R22), each linear in R's 9 entries (row by row) plus a constant:
# one product instead of some 60 picked entries and sums
_SHEPPERD = torch.tensor([
    # 1, R00, R01, R02, R10, R11, R12, R20, R21, R22
    [1, 1, 0, 0, 0, 1, 0, 0, 0, 1], [0, 0, 0, 0, 0, 0, -1, 0, 1, 0], [0, 0, 0, 1, 0, 0, 0, -1, 0, 0], [0, 0, -1, 0, 1, 0, 0, 0, 0, 0],
    [0, 0, 0, 0, 0, 0, -1, 0, 1, 0], [1, 1, 0, 0, 0, -1, 0, 0, 0, -1], [0, 0, 1, 0, 1, 0, 0, 0, 0, 0], [0, 0, 0, 1, 0, 0, 0, 1, 0, 0],
    [0, 0, 0, 1, 0, 0, 0, -1, 0, 0], [0, 0, 1, 0, 1, 0, 0, 0, 0, 0], [1, -1, 0, 0, 0, 1, 0, 0, 0, -1], [0, 0, 0, 0, 0, 0, 1, 0, 1, 0],
    [0, 0, -1, 0, 1, 0, 0, 0, 0, 0], [0, 0, 0, 1, 0, 0, 0, 1, 0, 0], [0, 0, 0, 0, 0, 0, 1, 0, 1, 0], [1, -1, 0, 0, 0, -1, 0, 0, 0, 1],
    [0, 1, 0, 0, 0, 1, 0, 0, 0, 1], [0, 1, 0, 0, 0, 0, 0, 0, 0, 0], [0, 0, 0, 0, 0, 1, 0, 0, 0, 0], [0, 0, 0, 0, 0, 0, 0, 0, 0, 1],
], dtype=torch.float64)


def matrix_to_quat(R: torch.Tensor) -> torch.Tensor:
    """Shepperd's method (branch on the largest diagonal term), returns w >= 0."""
    W = _SHEPPERD.to(R.dtype)
    y = torch.nn.functional.linear(R.reshape(*R.shape[:-2], 9), W[:, 1:], W[:, 0])
    cands = y[..., :16].reshape(*R.shape[:-2], 4, 4)  # (..., 4 candidates, 4)
    idx = y[..., 16:].argmax(-1)
    q = torch.gather(cands, -2, idx[..., None, None].expand(*idx.shape, 1, 4)).squeeze(-2)
    q = normalize(q)
    return torch.where(q[..., :1] < 0, -q, q)


def quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ),
        -1,
    )


def quat_slerp(a: torch.Tensor, b: torch.Tensor, t: torch.Tensor | float) -> torch.Tensor:
    """Shortest-path spherical interpolation; t broadcasts against the leading shape."""
    t = torch.as_tensor(t, dtype=a.dtype, device=a.device)
    if t.dim() == a.dim() - 1:
        t = t[..., None]
    dot = (a * b).sum(-1, keepdim=True)
    b = torch.where(dot < 0, -b, b)
    dot = dot.abs().clamp(max=1.0)
    theta = torch.acos(dot)
    sin = torch.sin(theta)
    lin = sin < 1e-6
    wa = torch.where(lin, 1 - t, torch.sin((1 - t) * theta) / sin.clamp_min(1e-12))
    wb = torch.where(lin, t, torch.sin(t * theta) / sin.clamp_min(1e-12))
    return normalize(wa * a + wb * b)


# ---------------------------------------------------------------- Euler
def _axis_matrix(axis: str, angle: torch.Tensor) -> torch.Tensor:
    c, s = torch.cos(angle), torch.sin(angle)
    o, z = torch.ones_like(angle), torch.zeros_like(angle)
    if axis == "X":
        m = (o, z, z, z, c, -s, z, s, c)
    elif axis == "Y":
        m = (c, z, s, z, o, z, -s, z, c)
    else:
        m = (c, -s, z, s, c, z, z, z, o)
    return torch.stack(m, -1).reshape(*angle.shape, 3, 3)


def check_order(order: str) -> str:
    order = order.upper()
    if len(order) != 3 or any(a not in _AXES for a in order):
        raise ValueError(f"Euler order {order!r} is not three of X, Y, Z (e.g. 'ZXY')")
    return order


def euler_to_matrix(angles: torch.Tensor, order: str) -> torch.Tensor:
    """angles[..., k] is the angle about order[k]; R = R_order[0] @ R_order[1] @ R_order[2]."""
    order = check_order(order)
    R = _axis_matrix(order[0], angles[..., 0])
    for k in (1, 2):
        R = R @ _axis_matrix(order[k], angles[..., k])
    return R


def matrix_to_euler(R: torch.Tensor, order: str) -> torch.Tensor:
    """Inverse of euler_to_matrix for all 12 orders (Tait-Bryan and proper Euler)."""
    order = check_order(order)
    i, j, k = (_AXES[a] for a in order)
    if i == k:
        return _matrix_to_proper_euler(R, i, j)
    # Tait-Bryan: R = R_i(a) R_j(b) R_k(c); sign of the permutation decides the signs
    sign = 1.0 if (j - i) % 3 == 1 else -1.0
    sb = (sign * R[..., i, k]).clamp(-1.0, 1.0)
    b = torch.asin(sb)
    a = torch.atan2(-sign * R[..., j, k], R[..., k, k])
    c = torch.atan2(-sign * R[..., i, j], R[..., i, i])
    # gimbal lock: put everything into a
    lock = sb.abs() > 1 - 1e-9
    a_lock = torch.atan2(sign * R[..., k, j], R[..., j, j])
    a = torch.where(lock, a_lock, a)
    c = torch.where(lock, torch.zeros_like(c), c)
    return torch.stack((a, b, c), -1)


def _matrix_to_proper_euler(R: torch.Tensor, i: int, j: int) -> torch.Tensor:
    # R = R_i(a) R_j(b) R_i(c), k the remaining axis
    k = 3 - i - j
    sign = 1.0 if (j - i) % 3 == 1 else -1.0
    cb = R[..., i, i].clamp(-1.0, 1.0)
    b = torch.acos(cb)
    a = torch.atan2(R[..., j, i], -sign * R[..., k, i])
    c = torch.atan2(R[..., i, j], sign * R[..., i, k])
    lock = (cb.abs() > 1 - 1e-9)
    a_lock = torch.atan2(sign * R[..., k, j], R[..., j, j])
    a = torch.where(lock, a_lock, a)
    c = torch.where(lock, torch.zeros_like(c), c)
    return torch.stack((a, b, c), -1)


# ---------------------------------------------------------------- helpers
def rotation_between(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Smallest rotation matrix taking direction u onto direction v (antiparallel handled)."""
    u, v = normalize(u), normalize(v)
    axis = torch.cross(u, v, dim=-1)
    s = axis.norm(dim=-1, keepdim=True)
    c = (u * v).sum(-1, keepdim=True)
    angle = torch.atan2(s, c)
    # antiparallel: rotate pi about any axis perpendicular to u
    ref = torch.where(u[..., :1].abs() < 0.9, torch.tensor([1.0, 0, 0], dtype=u.dtype), torch.tensor([0, 1.0, 0], dtype=u.dtype))
    perp = normalize(torch.cross(u, ref, dim=-1))
    axis = torch.where(s < 1e-9, perp, axis / s.clamp_min(1e-12))
    return axis_angle_to_matrix(axis * angle)


def turn_onto(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """rotation_between for directions that are never near opposite (small corrections, as the
    legs' IK makes): R = I + [w]x + [w]x^2 / (1 + c), with w = u x v and c = u . v of the unit
    directions, in a third of rotation_between's operations; near opposite it is not a rotation."""
    u, v = normalize(u), normalize(v)
    K = skew(torch.cross(u, v, dim=-1))
    c = (u * v).sum(-1)[..., None, None]
    return torch.eye(3, dtype=u.dtype, device=u.device) + K + (K @ K) / (1 + c).clamp_min(1e-6)


def kabsch(src: torch.Tensor, dst: torch.Tensor, weights: torch.Tensor | None = None) -> torch.Tensor:
    """Rotation R minimising sum_k w_k |R src_k - dst_k|^2 (src, dst: (..., K, 3), no centring)."""
    if weights is None:
        weights = torch.ones(src.shape[:-1], dtype=src.dtype)
    H = (src * weights[..., None]).transpose(-1, -2) @ dst  # 3x3
    U, _, Vt = torch.linalg.svd(H)
    d = torch.sign(torch.linalg.det(Vt.transpose(-1, -2) @ U.transpose(-1, -2)))
    D = torch.diag_embed(torch.stack((torch.ones_like(d), torch.ones_like(d), d), -1))
    return Vt.transpose(-1, -2) @ D @ U.transpose(-1, -2)


def yaw_matrix(angle: torch.Tensor) -> torch.Tensor:
    """Rotation about +Y (world up) by angle (radians)."""
    return _axis_matrix("Y", angle)
