"""Persona conditions of the one denoiser (MotionPersona §5.1-5.3, our design).

Three conditions:
- text: a sentence embedding of who the character is (`model/text.py`, 256-d), unit length;
- shape: the body-shape vector (body/skeleton.py SHAPE_NAMES);
- trajectory: where the root goes over the segment's frames, in the segment's canonical frame:
  ground position (x, z) and facing (sin, cos of the yaw) per frame.
Text and shape are added to the condition token (time + initial state), the trajectory frame by
frame to the frame tokens. MotionPersona gives each condition a token of its own; tried here as
three extra tokens warm-started from the base, they were not attended: after 4,000 steps the
denoising loss with and without all three differed by under 1 % and their gradients were 100x
smaller than the base's, so the text changed nothing (character classification at chance).

Each may be absent and then adds nothing, so a denoiser given none is the base computation
exactly (a warm start from a base is that base at its first step), and the same model moves by
itself, takes impulses and adaptors, when no persona is set.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from ..body import rotations as rot
from ..body.motion_state import SLICES
from ..body.skeleton import SHAPE_DIM

TEXT_DIM = 256
CONDITIONS = ("text", "shape", "trajectory")
TRAJ_FEATURES = 4  # x, z, sin yaw, cos yaw


@dataclass
class PersonaCond:
    """Batched persona conditions. `present` (B, 3) bool says which of CONDITIONS each row has;
    the values of an absent condition are ignored (zeros by convention)."""
    text: torch.Tensor  # (B, TEXT_DIM)
    shape: torch.Tensor  # (B, SHAPE_DIM)
    trajectory: torch.Tensor  # (B, frames, TRAJ_FEATURES)
    present: torch.Tensor  # (B, 3) bool

    def __len__(self) -> int:
        return len(self.present)

    def select(self, rows) -> "PersonaCond":
        return PersonaCond(self.text[rows], self.shape[rows], self.trajectory[rows], self.present[rows])

    def without(self, which: str) -> "PersonaCond":
        """The same conditions with `which` absent in every row (for guidance and ablations)."""
        present = self.present.clone()
        present[:, CONDITIONS.index(which)] = False
        return PersonaCond(self.text, self.shape, self.trajectory, present)

    @staticmethod
    def cat(parts: list["PersonaCond"]) -> "PersonaCond":
        return PersonaCond(*(torch.cat([getattr(p, f) for p in parts]) for f in ("text", "shape", "trajectory", "present")))


def trajectory_of(x: torch.Tensor) -> torch.Tensor:
    """The trajectory condition (B, N, 4) of canonical states (B, N, 267), unnormalized: the root's
    ground position and the facing of its forward (+Z) axis on the ground."""
    R = rot.sixd_to_matrix(x[..., SLICES["root_rot"]])
    fwd = R[..., :, 2]  # the body's forward axis in the canonical frame
    yaw = torch.atan2(fwd[..., 0], fwd[..., 2])
    pos = x[..., SLICES["root_pos"]]
    return torch.stack((pos[..., 0], pos[..., 2], torch.sin(yaw), torch.cos(yaw)), -1)


class PersonaEmbedding(nn.Module):
    """Text and shape as vectors added to the condition token, the trajectory as one vector per
    frame added to that frame's token; each embedder ends in a zero-initialised layer and an absent
    condition adds nothing, so a network fresh from its base is that base exactly."""

    def __init__(self, width: int):
        super().__init__()

        def mlp(n):
            m = nn.Sequential(nn.Linear(n, width), nn.SiLU(), nn.Linear(width, width))
            nn.init.zeros_(m[2].weight)
            nn.init.zeros_(m[2].bias)
            return m
        self.text, self.shape, self.trajectory = mlp(TEXT_DIM), mlp(SHAPE_DIM), mlp(TRAJ_FEATURES)

    def forward(self, c: PersonaCond, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, width) for the condition token, (B, frames, width) for the frame tokens."""
        on = c.present.to(dtype)
        # a unit text vector is scaled so its entries have about unit variance, as the others
        text = nn.functional.normalize(c.text.to(dtype), dim=-1) * TEXT_DIM ** 0.5
        cond = on[:, :1] * self.text(text) + on[:, 1:2] * self.shape(c.shape.to(dtype))
        return cond, on[:, 2, None, None] * self.trajectory(c.trajectory.to(dtype))
