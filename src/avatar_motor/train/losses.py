"""PRIMAL Eq. 4-6: L = L_simple + g1 L_FK + g2 L_FKV, the FK terms through the one FK of body/
with each sample's body shape.

Units: L_simple is on normalized states; L_FK on joint positions in metres (weight `fk`);
L_FKV on joint velocities in m/s (weight `fkv`). Defaults are set in TrainConfig.
"""
from __future__ import annotations

import torch

from ..body import rotations as rot
from ..body.skeleton import forward_kinematics, rest_offsets
from ..data.dataset import Normalizer
from ..body.motion_state import FPS, SLICES, joints_of, velocities_of


def fk_joints(x: torch.Tensor, shapes: torch.Tensor) -> torch.Tensor:
    """Joint positions (B, T, 22, 3) from the rotation part of states (B, T, 267) via FK."""
    B, T, _ = x.shape
    root_pos = x[..., SLICES["root_pos"]]
    root_rot = rot.sixd_to_matrix(x[..., SLICES["root_rot"]])
    local = rot.sixd_to_matrix(x[..., SLICES["local_rot"]].reshape(B, T, 21, 6))
    off = rest_offsets(shapes, x.dtype)[:, None]
    return forward_kinematics(root_pos, root_rot, local, off)[0]


def motion_loss(x0_hat_n: torch.Tensor, target_n: torch.Tensor, x_init: torch.Tensor, shapes: torch.Tensor,
                norm: Normalizer, fk: float, fkv: float) -> dict[str, torch.Tensor]:
    """x0_hat_n, target_n: normalized (B, N, 267); x_init: the real (unnormalized) initial state (B, 267)."""
    simple = ((x0_hat_n - target_n) ** 2).mean()
    x_hat = norm.decode(x0_hat_n)
    target = norm.decode(target_n)
    J_hat = fk_joints(x_hat, shapes)
    J = joints_of(target)
    l_fk = ((J_hat - J) ** 2).sum(-1).mean()
    prev = torch.cat((joints_of(x_init)[:, None], J_hat[:, :-1]), 1)
    v_hat = (J_hat - prev) * FPS
    l_fkv = ((v_hat - velocities_of(target)) ** 2).sum(-1).mean()
    total = simple + fk * l_fk + fkv * l_fkv
    return {"loss": total, "simple": simple.detach(), "fk": l_fk.detach(), "fkv": l_fkv.detach()}


# a foot joint is planted where the real motion holds it low and still: EMDM's contact mask f_i
CONTACT_HEIGHT = 0.12  # metres above the ground (the ankles stand at about 8 cm)
CONTACT_SPEED = 0.3  # m/s


def foot_loss(x0_hat_n: torch.Tensor, target_n: torch.Tensor, x_init: torch.Tensor, shapes: torch.Tensor,
              norm: Normalizer) -> torch.Tensor:
    """EMDM Eq. 9: the speed (m/s) of the generated body's ankles and feet (FK of its rotations)
    squared, where the real segment has them planted."""
    from ..body.skeleton import ANKLES_AND_FEET
    J_hat = fk_joints(norm.decode(x0_hat_n), shapes)[:, :, ANKLES_AND_FEET]
    J = joints_of(norm.decode(target_n))[:, :, ANKLES_AND_FEET]
    first = joints_of(x_init)[:, None, ANKLES_AND_FEET]
    v_hat = (J_hat - torch.cat((first, J_hat[:, :-1]), 1)) * FPS
    v = (J - torch.cat((first, J[:, :-1]), 1)) * FPS
    planted = ((J[..., 1] < CONTACT_HEIGHT) & (v.norm(dim=-1) < CONTACT_SPEED)).to(v_hat.dtype)
    return ((v_hat ** 2).sum(-1) * planted).mean()
