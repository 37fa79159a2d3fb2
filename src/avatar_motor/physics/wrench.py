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
import torch

from ..body.skeleton import NUM_JOINTS
from .solver import H, REST_HEIGHT
PYRAMID_EDGES = 4  # friction cone approximated by a 4-sided pyramid (Zheng and Yamane 2013)
CONTACT_HEIGHT = 0.03  # m above its resting height a joint still touches the ground


def nnls(A: np.ndarray, b: np.ndarray, max_iter: int | None = None, start: np.ndarray | None = None) -> np.ndarray:
    """min |A x - b| subject to x >= 0 (Lawson and Hanson's active-set method). start (n,) bool:
    a guess of the columns the solution uses (e.g. the frame before's); taken as the first
    passive set when its least squares is positive, which leaves one or two rounds to do."""
    m, n = A.shape
    x = np.zeros(n)
    passive = np.zeros(n, dtype=bool)
    tol = 10 * np.finfo(float).eps * max(1.0, np.abs(A).max()) * max(m, n)
    if start is not None and start.any():
        Ap = A[:, start]
        z = np.linalg.lstsq(Ap, b, rcond=None)[0]
        if (z > tol).all():
            x[start], passive = z, start.copy()
    w = A.T @ (b - A @ x)
    for _ in range(max_iter or 3 * n):
        if passive.all() or (w[~passive] <= tol).all():
            break
        j = np.argmax(np.where(passive, -np.inf, w))
        passive[j] = True
        for _ in range(n + 1):  # each round drops at least one coefficient from the passive set
            z = np.zeros(n)
            Ap = A[:, passive]
            try:  # the passive columns' least squares, by the normal equations (a few columns)
                z[passive] = np.linalg.solve(Ap.T @ Ap, Ap.T @ b)
            except np.linalg.LinAlgError:
                z[passive] = np.linalg.lstsq(Ap, b, rcond=None)[0]
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
    if not len(points):
        return np.zeros((6, 0))
    r = np.repeat(points - com, PYRAMID_EDGES, axis=0)  # (C * 4, 3), point-major
    e = np.tile(edges, (len(points), 1))
    return np.concatenate((e, np.cross(r, e)), axis=1).T


def momentum_map(x_t: np.ndarray, v_t: np.ndarray, masses: np.ndarray, gravity: float,
                 forces: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """B (6, 66) and a (6,) with b = B x - a the wrench the ground must supply for the next frame
    x (66, joint-major): (sum m a - M g - f_ext, sum m r x a - sum r x f_ext), a_j = ((x_j - x_t_j)/h
    - v_t_j)/h, moment arms r about the centre of mass at x_t (DROP Eq. 12-13)."""
    com = (masses[:, None] * x_t).sum(0) / masses.sum()
    r = x_t - com
    k = masses / H**2
    skew = np.zeros((NUM_JOINTS, 3, 3))  # skew[j] @ u = r_j x u
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -r[:, 2], r[:, 1], -r[:, 0]
    skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = r[:, 2], -r[:, 1], r[:, 0]
    B = np.concatenate((np.broadcast_to(np.eye(3), (NUM_JOINTS, 3, 3)), skew), axis=1) * k[:, None, None]  # (22, 6, 3)
    B = B.transpose(1, 0, 2).reshape(6, 3 * NUM_JOINTS)
    base = masses[:, None] * (x_t / H**2 + v_t / H)  # the part of m a_j not depending on x
    a = np.concatenate((base.sum(0), np.cross(r, base).sum(0)))
    a[:3] += masses.sum() * np.array([0.0, -gravity, 0.0])  # gravity supplies that much: not the ground
    if forces is not None:
        a[:3] += forces.sum(0)
        a[3:] += np.cross(r, forces).sum(0)
    return B, a


def root_wrench(x: np.ndarray, x_t: np.ndarray, v_t: np.ndarray, masses: np.ndarray, contact: np.ndarray,
                gravity: float, mu: float, forces: np.ndarray | None = None, guess: np.ndarray | None = None,
                enough: float = 0.0) -> tuple[float, np.ndarray, dict]:
    """The metric |b - F c| (N and N m together) for the next frame x (22, 3) after x_t, v_t,
    with contact (22,) bool the joints touching the ground at x_t. Returns it, F c (6,) and the
    pieces the correction reuses (with "c": the contact forces per joint and pyramid edge, (22, 4)).
    guess (22, 4), e.g. the frame before's contact forces: when they leave a residual of at most
    `enough`, that residual is returned (the metric is no larger) and the NNLS is skipped."""
    B, a = momentum_map(x_t, v_t, masses, gravity, forces)
    b = B @ x.reshape(-1) - a
    com = (masses[:, None] * x_t).sum(0) / masses.sum()
    F = friction_basis(x_t[contact], com, mu)
    per_joint = np.zeros((NUM_JOINTS, PYRAMID_EDGES))
    if guess is not None and F.shape[1]:
        c = guess[contact].reshape(-1)
        metric = float(np.linalg.norm(b - F @ c))
        if metric <= enough:  # any c >= 0 bounds the metric from above
            per_joint[contact] = guess[contact]
            return metric, F @ c, {"B": B, "a": a, "b": b, "c": per_joint}
    start = None if guess is None else guess[contact].reshape(-1) > 0
    c = nnls(F, b, start=start) if F.shape[1] else np.zeros(0)
    Fc = F @ c
    per_joint[contact] = c.reshape(-1, PYRAMID_EDGES)
    return float(np.linalg.norm(b - Fc)), Fc, {"B": B, "a": a, "b": b, "c": per_joint}


def soft_correction(x_pd: np.ndarray, x_t: np.ndarray, v_t: np.ndarray, masses: np.ndarray, contact: np.ndarray,
                    gravity: float, mu: float, weight: float, skip_below: float,
                    forces: np.ndarray | None = None, max_move: float | None = None,
                    guess: np.ndarray | None = None) -> tuple[np.ndarray, float, float, np.ndarray]:
    """DROP Eq. 14 on the solved frame x_pd (22, 3): the closest frame whose residual wrench is
    reduced by the weight w (0: none; large: all of it), unless the metric is below skip_below;
    with max_move, scaled down so that no joint moves farther (m). guess: as root_wrench's.
    Returns the frame, the metric before and after (with the contact forces of before) and the
    contact forces (22, 4)."""
    before, Fc, p = root_wrench(x_pd, x_t, v_t, masses, contact, gravity, mu, forces, guess, skip_below)
    if before <= skip_below or weight <= 0:
        return x_pd, before, before, p["c"]
    B, r = p["B"], p["b"] - Fc
    # the joints on the ground stay where static friction holds them: moved, they skated
    # (eval physics: ASR 0.03 -> 0.07 unperturbed, 0.11 -> 0.19 after a 200 N s push)
    Bf = B * np.repeat(~contact, 3)[None]
    K = np.eye(6) / weight + Bf @ Bf.T
    move = -(Bf.T @ np.linalg.solve(K, r)).reshape(NUM_JOINTS, 3)
    far = np.linalg.norm(move, axis=1).max()
    if max_move is not None and far > max_move:
        move *= max_move / far
    after = float(np.linalg.norm(r + B @ move.reshape(-1)))  # b is affine in x: the residual moves by B dx
    return x_pd + move, before, after, p["c"]


def contacts(x: np.ndarray) -> np.ndarray:
    """(22,) bool: the joints of x (22, 3) touching the ground (within CONTACT_HEIGHT of resting)."""
    return x[:, 1] < REST_HEIGHT.numpy() + CONTACT_HEIGHT


def correct(x_pd, x_t, v_t, masses, forces, cfg, guess: np.ndarray | None = None, which: list[bool] | None = None):
    """DROP §6 for a batch: each solved frame x_pd (B, 22, 3) after x_t, v_t (torch, world) with
    masses (B, 22) and external forces (B, 22, 3) N, corrected by `soft_correction` where its
    root-wrench metric is above cfg.ghost_threshold body weights. guess (B, 22, 4): the contact
    forces of the frame before (skips most NNLS); which: the bodies to correct (None: all; the
    others are left as they are, with 0 for their figures). Returns the frames (torch), the metric before
    and after (B,) in body weights (an upper bound where below the threshold) and the contact
    forces (B, 22, 4)."""
    out = x_pd.clone()
    before, after = np.zeros(len(x_pd)), np.zeros(len(x_pd))
    c = np.zeros((len(x_pd), NUM_JOINTS, PYRAMID_EDGES))
    for b in range(len(x_pd)):
        if which is not None and not which[b]:
            continue
        m = masses[b].double().numpy()
        weight = m.sum() * cfg.gravity
        xt = x_t[b].double().numpy()
        x, before[b], after[b], c[b] = soft_correction(
            x_pd[b].double().numpy(), xt, v_t[b].double().numpy(), m, contacts(xt), cfg.gravity, cfg.friction,
            cfg.correction, cfg.ghost_threshold * weight, forces[b].double().numpy(), cfg.correction_step,
            None if guess is None else guess[b])
        out[b] = torch.from_numpy(x).to(out.dtype)
        before[b], after[b] = before[b] / weight, after[b] / weight
    return out, before, after, c
