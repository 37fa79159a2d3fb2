"""Persona conditions as tokens of the one denoiser (MotionPersona §5.1-5.3, our design).

Three conditions, each one token placed after the condition token and before the frames:
- text: a sentence embedding of who the character is (`model/text.py`, 256-d), unit length;
- shape: the body-shape vector (body/skeleton.py SHAPE_NAMES);
- trajectory: where the root goes over the segment's frames, in the segment's canonical frame:
  ground position (x, z) and facing (sin, cos of the yaw) per frame.

Each may be absent. An absent condition is masked out of attention, so a denoiser given none is
the base computation exactly (a warm start from a base is that base at its first step), and the
same model moves by itself, takes impulses and adaptors, when no persona is set.
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

    @staticmethod
    def make(batch: int, frames: int, text: torch.Tensor | None = None, shape: torch.Tensor | None = None,
             trajectory: torch.Tensor | None = None) -> "PersonaCond":
        """Conditions for `batch` rows; a condition given as None is absent for every row."""
        present = torch.tensor([text is not None, shape is not None, trajectory is not None]).expand(batch, 3).clone()
        return PersonaCond(
            text if text is not None else torch.zeros(batch, TEXT_DIM),
            shape if shape is not None else torch.zeros(batch, SHAPE_DIM),
            trajectory if trajectory is not None else torch.zeros(batch, frames, TRAJ_FEATURES),
            present)

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


class PersonaTokens(nn.Module):
    """The three condition tokens (B, 3, width) and a key mask (B, 3) of the present ones."""

    def __init__(self, width: int, frames: int):
        super().__init__()
        self.text = nn.Sequential(nn.Linear(TEXT_DIM, width), nn.SiLU(), nn.Linear(width, width))
        self.shape = nn.Sequential(nn.Linear(SHAPE_DIM, width), nn.SiLU(), nn.Linear(width, width))
        self.trajectory = nn.Sequential(nn.Linear(frames * TRAJ_FEATURES, width), nn.SiLU(), nn.Linear(width, width))
        self.kind = nn.Parameter(torch.randn(1, 3, width) * 0.02)  # which condition a token is

    def forward(self, c: PersonaCond, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
        # a unit text vector is scaled so its entries have about unit variance, as the others
        text = nn.functional.normalize(c.text.to(dtype), dim=-1) * TEXT_DIM ** 0.5
        tok = torch.stack((self.text(text), self.shape(c.shape.to(dtype)),
                           self.trajectory(c.trajectory.to(dtype).flatten(1))), 1)
        return tok + self.kind.to(dtype), c.present
