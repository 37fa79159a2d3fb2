"""DROP §6: the root-wrench metric and its soft correction.

The change of the body's linear and angular momentum (about its centre of mass) over a frame,
less what gravity and the external forces explain, must come from the ground through its
contacts. b = (dP, dL) - (gravity, external) is affine in the next frame's joints x (Eq. 12-13:
b = B x - a, with the moment arms and the contacts taken at x_t). The contact forces that best
explain it are a non-negative combination c of the edges of each contact's friction pyramid
(Eq. 11, non-negative least squares). What is left, |b - F c|, is force no contact can give:
the "magic" with which a kinematic prior rights a body. The soft correction moves the solved
frame the least that removes part of it (Eq. 14):

    min_x,e |x - x_pd|^2 + w |e|^2  subject to  B x - a - F c = e

whose KKT solution is x = x_pd - B^T (I / w + B B^T)^-1 (B x_pd - a - F c) (a 6 x 6 system).
It is skipped when the metric is within what real motion shows (finite differences of mocap
carry some too, DROP Fig. 7).

Per body: numpy float64 (NNLS has no batched form); the sizes are 6 x at most 88."""
from __future__ import annotations

import numpy as np

from ..body.skeleton import NUM_JOINTS
from .solver import H
PYRAMID_EDGES = 4  # friction cone approximated by a 4-sided pyramid (Zheng and Yamane 2013)


def nnls(A: np.ndarray, b: np.ndarray, max_iter: int | None = None) -> np.ndarray:
    """min |A x - b| subject to x >= 0 (Lawson and Hanson's active-set method)."""
    m, n = A.shape
    x = np.zeros(n)
    passive = np.zeros(n, dtype=bool)
    w = A.T @ (b - A @ x)
    tol = 10 * np.finfo(float).eps * max(1.0, np.abs(A).max()) * max(m, n)
    for _ in range(max_iter or 3 * n):
        if passive.all() or (w[~passive] <= tol).all():
            break
        j = np.argmax(np.where(passive, -np.inf, w))
        passive[j] = True
        for _ in range(n + 1):  # each round drops at least one coefficient from the passive set
            z = np.zeros(n)
            z[passive] = np.linalg.lstsq(A[:, passive], b, rcond=None)[0]
            if (z[passive] > tol).all():
                break
            neg = passive & (z <= tol)
            alpha = np.min(x[neg] / np.maximum(x[neg] - z[neg], 1e-300))
            x = x + alpha * (z - x)
            passive &= x > tol
            x[~passive] = 0.0
        x = z
        w = A.T @ (b - A @ x)
    return x


def friction_basis(points: np.ndarray, com: np.ndarray, mu: float) -> np.ndarray:
    """(6, PYRAMID_EDGES * C): for each contact point (C, 3) the wrenches (force; torque about
    the centre of mass com (3,)) of the unit edges of its friction pyramid (ground normal +y,
    friction coefficient mu)."""
    edges = np.array([[mu, 1.0, 0.0], [-mu, 1.0, 0.0], [0.0, 1.0, mu], [0.0, 1.0, -mu]])
    edges /= np.linalg.norm(edges, axis=1, keepdims=True)
    cols = []
    for p in points:
        r = p - com
        for e in edges:
            cols.append(np.concatenate((e, np.cross(r, e))))
    return np.array(cols).T if cols else np.zeros((6, 0))


def _skew(r: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])


def momentum_map(x_t: np.ndarray, v_t: np.ndarray, masses: np.ndarray, gravity: float,
                 forces: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """B (6, 66) and a (6,) with b = B x - a the wrench the ground must supply for the next frame
    x (66, joint-major): (sum m a - M g - f_ext, sum m r x a - sum r x f_ext), a_j = ((x_j - x_t_j)/h
    - v_t_j)/h, moment arms r about the centre of mass at x_t (DROP Eq. 12-13)."""
    com = (masses[:, None] * x_t).sum(0) / masses.sum()
    r = x_t - com
    B = np.zeros((6, 3 * NUM_JOINTS))
    a = np.zeros(6)
    for j in range(NUM_JOINTS):
        k = masses[j] / H**2
        B[:3, 3 * j:3 * j + 3] = k * np.eye(3)
        B[3:, 3 * j:3 * j + 3] = k * _skew(r[j])
        base = masses[j] * (x_t[j] / H**2 + v_t[j] / H)  # the part of m a_j not depending on x
        a[:3] += base
        a[3:] += _skew(r[j]) @ base
    a[:3] += masses.sum() * np.array([0.0, -gravity, 0.0])  # gravity supplies that much: not the ground
    if forces is not None:
        a[:3] += forces.sum(0)
        a[3:] += np.cross(r, forces).sum(0)
    return B, a


def root_wrench(x: np.ndarray, x_t: np.ndarray, v_t: np.ndarray, masses: np.ndarray, contact: np.ndarray,
                gravity: float, mu: float, forces: np.ndarray | None = None) -> tuple[float, np.ndarray, dict]:
    """The metric |b - F c| (N and N m together) for the next frame x (22, 3) after x_t, v_t,
    with contact (22,) bool the joints touching the ground at x_t. Returns it, F c (6,) and the
    pieces the correction reuses."""
    B, a = momentum_map(x_t, v_t, masses, gravity, forces)
    b = B @ x.reshape(-1) - a
    com = (masses[:, None] * x_t).sum(0) / masses.sum()
    F = friction_basis(x_t[contact], com, mu)
    c = nnls(F, b) if F.shape[1] else np.zeros(0)
    Fc = F @ c
    return float(np.linalg.norm(b - Fc)), Fc, {"B": B, "a": a, "b": b}


def soft_correction(x_pd: np.ndarray, x_t: np.ndarray, v_t: np.ndarray, masses: np.ndarray, contact: np.ndarray,
                    gravity: float, mu: float, weight: float, skip_below: float,
                    forces: np.ndarray | None = None) -> tuple[np.ndarray, float, float]:
    """DROP Eq. 14 on the solved frame x_pd (22, 3): the closest frame whose residual wrench is
    reduced by the weight w (0: none; large: all of it), unless the metric is below skip_below.
    Returns the frame and the metric before and after."""
    before, Fc, p = root_wrench(x_pd, x_t, v_t, masses, contact, gravity, mu, forces)
    if before <= skip_below or weight <= 0:
        return x_pd, before, before
    B, r = p["B"], p["b"] - Fc
    K = np.eye(6) / weight + B @ B.T
    x = x_pd.reshape(-1) - B.T @ np.linalg.solve(K, r)
    x = x.reshape(NUM_JOINTS, 3)
    after = float(np.linalg.norm(B @ x.reshape(-1) - p["a"] - Fc))
    return x, before, after
