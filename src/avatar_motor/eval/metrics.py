"""Motion metrics (DESIGN §7; PRIMAL §5.1.1, supplementary §9.2-9.3). All take world joint
positions (..., T, 22, 3) at 30 fps unless said otherwise."""
from __future__ import annotations

import torch

from ..body.skeleton import JOINT_INDEX
from ..body.motion_state import FPS

FEET = [JOINT_INDEX["left_foot"], JOINT_INDEX["right_foot"]]


def skating_frames(J: torch.Tensor, height: float = 0.05, speed: float = 0.15) -> torch.Tensor:
    """A frame skates when both foot joints are within `height` of the ground and both move
    horizontally faster than `speed` (m/s). Returns a bool (..., T-1)."""
    f = J[..., FEET, :]
    v = (f[..., 1:, :, :] - f[..., :-1, :, :])[..., [0, 2]].norm(dim=-1) * FPS
    low = f[..., 1:, :, 1] < height
    return (low & (v > speed)).all(-1)


def asr(J: torch.Tensor) -> float:
    return float(skating_frames(J).float().mean())


def ancr(J: torch.Tensor, depth: float = 0.05) -> float:
    """Fraction of frames whose lowest joint is not more than `depth` below the ground."""
    return float((J[..., 1].amin(-1) > -depth).float().mean())


def jerks(J: torch.Tensor) -> torch.Tensor:
    """(..., T - 3, 22) jerk magnitude (m/s^3) of joints J (..., T, 22, 3) over each window of four
    frames t..t+3 (third differences)."""
    d3 = J[..., 3:, :, :] - 3 * J[..., 2:-1, :, :] + 3 * J[..., 1:-2, :, :] - J[..., :-3, :, :]
    return d3.norm(dim=-1) * FPS**3


def jitter(J: torch.Tensor) -> float:
    """Mean jerk magnitude (m/s^3), third differences of joint positions."""
    return float(jerks(J).mean())


def join_jerk(J: torch.Tensor, joins: list[list[int]]) -> float:
    """How much rougher the motion is across segment joins than within segments: the mean jerk
    magnitude of the third differences that span a join (frames j-1 and j for a join at frame j)
    over that of all the others (1 for motion without seams). J (B, T, 22, 3); joins: per row, the
    frames where a segment starts (eval.realism.rollout's joins_out)."""
    d3 = jerks(J).mean(-1)  # (B, T-3): window t..t+3
    spans = torch.zeros_like(d3, dtype=torch.bool)
    for b, js in enumerate(joins):
        for j in js:
            spans[b, max(0, j - 3):max(0, min(j, d3.shape[1]))] = True  # windows t with t <= j-1 < j <= t+3
    if not bool(spans.any()) or bool(spans.all()):
        raise ValueError("join_jerk needs frames both across and away from the joins")
    return float(d3[spans].mean() / d3[~spans].mean())


def mean_joint_speed(J: torch.Tensor) -> torch.Tensor:
    """Per-frame mean joint speed (..., T-1) in m/s."""
    return (J[..., 1:, :, :] - J[..., :-1, :, :]).norm(dim=-1).mean(-1) * FPS


def alive_ratio(J: torch.Tensor, threshold: float = 0.1) -> float:
    """Fraction of 1-s windows in which the mean joint speed exceeds `threshold` m/s."""
    s = mean_joint_speed(J)
    w = int(FPS)
    n = s.shape[-1] // w
    if n == 0:
        return float("nan")
    win = s[..., : n * w].reshape(*s.shape[:-1], n, w).mean(-1)
    return float((win > threshold).float().mean())


def frozen(J: torch.Tensor, seconds: float = 3.0, threshold: float = 0.005) -> torch.Tensor:
    """True per sequence when the body is perfectly still (mean joint speed < threshold) for
    `seconds` in a row: the model has stopped generating motion (standing still breathes)."""
    still = (mean_joint_speed(J) < threshold).float()
    k = int(seconds * FPS)
    if still.shape[-1] < k:
        return torch.zeros(still.shape[:-1], dtype=torch.bool)
    runs = still.unfold(-1, k, 1).amin(-1)
    return runs.amax(-1) > 0


def mirror_local_rotations(R: torch.Tensor) -> torch.Tensor:
    """Local rotations (..., 21, 3, 3) of the left/right mirrored pose (the augmentation the
    model trains with): M R M with M = diag(-1, 1, 1), left and right joints swapped."""
    from ..body.skeleton import MIRROR
    M_ = torch.diag(torch.tensor([-1.0, 1.0, 1.0], dtype=R.dtype))
    return (M_ @ R @ M_)[..., [MIRROR[j + 1] - 1 for j in range(21)], :, :]


def pose_features(local_rot: torch.Tensor) -> torch.Tensor:
    """(..., 21, 3, 3) -> (..., 189): flattened joint rotations (chordal distance space)."""
    return local_rot.reshape(*local_rot.shape[:-3], -1)


def nn_pose_distance(query: torch.Tensor, reference: torch.Tensor, chunk: int = 2048) -> torch.Tensor:
    """Per query pose, the distance to its nearest reference pose: sqrt(mean over joints of the
    squared Frobenius distance of the rotations). query (Q, 189), reference (R, 189)."""
    out = []
    for i in range(0, len(query), chunk):
        d = torch.cdist(query[i:i + chunk], reference)
        out.append(d.min(-1).values)
    return torch.cat(out) / (21**0.5)
