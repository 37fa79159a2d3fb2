"""The canonical 22-joint body (SMPL joint order and names) with our own rest skeleton.

World: Y up, metres, right-handed; the rest body faces +Z with its left side towards +X.
Rest pose: a T-pose-like stance in which every joint frame is aligned with the world (all
rotations identity), so a global joint rotation says directly how a bone is turned.

Body shape is a small vector of interpretable parameters, zero = an average adult (1.69 m):

| index | name           | unit of one step                                           |
|-------|----------------|------------------------------------------------------------|
| 0     | stature        | 10 cm of standing height (whole body scales uniformly)     |
| 1     | leg_length     | +5 % of thigh, shin and foot-drop lengths                  |
| 2     | torso_length   | +5 % of spine, neck and head lengths                       |
| 3     | arm_length     | +5 % of upper arm and forearm lengths                      |
| 4     | shoulder_width | +8 % of collar and shoulder sideways offsets               |
| 5     | hip_width      | +8 % of hip sideways offsets                               |

Random shapes for augmentation are drawn from N(0, I) clipped to +-2.5 (`random_shapes`).
"""
from __future__ import annotations

import torch

JOINT_NAMES = [
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck",
    "left_collar", "right_collar", "head", "left_shoulder", "right_shoulder",
    "left_elbow", "right_elbow", "left_wrist", "right_wrist",
]
NUM_JOINTS = 22
PARENTS = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19]
JOINT_INDEX = {n: i for i, n in enumerate(JOINT_NAMES)}
ANKLES_AND_FEET = [JOINT_INDEX[n] for n in ("left_ankle", "right_ankle", "left_foot", "right_foot")]
SHAPE_NAMES = ["stature", "leg_length", "torso_length", "arm_length", "shoulder_width", "hip_width"]
SHAPE_DIM = len(SHAPE_NAMES)
# left/right partner of every joint (for mirroring)
MIRROR = [JOINT_INDEX[n.replace("left_", "@").replace("right_", "left_").replace("@", "right_")] for n in JOINT_NAMES]

# Offsets of each joint from its parent in the rest pose, metres, average adult (our own numbers).
_L = {  # left side; the right side mirrors x
    "hip": (0.060, -0.085, -0.015), "knee": (0.040, -0.385, 0.005), "ankle": (-0.010, -0.420, -0.035),
    "foot": (0.035, -0.060, 0.125), "collar": (0.075, 0.115, -0.020), "shoulder": (0.120, 0.045, -0.015),
    "elbow": (0.255, -0.015, -0.025), "wrist": (0.265, 0.010, -0.005),
}
_C = {"spine1": (0.0, 0.110, -0.020), "spine2": (0.0, 0.135, 0.020), "spine3": (0.0, 0.055, 0.0),
      "neck": (0.0, 0.210, -0.030), "head": (0.0, 0.090, 0.050)}
FOOT_CLEARANCE = 0.02  # height of the foot (toe) joint above the ground when standing, metres
SKULL = 0.12  # top of the head above the head joint, metres


def _template() -> torch.Tensor:
    off = torch.zeros(NUM_JOINTS, 3, dtype=torch.float64)
    for i, name in enumerate(JOINT_NAMES[1:], start=1):
        if name in _C:
            off[i] = torch.tensor(_C[name])
        else:
            side, part = name.split("_", 1)
            v = torch.tensor(_L[part])
            off[i] = v if side == "left" else v * torch.tensor([-1.0, 1.0, 1.0])
    return off


TEMPLATE_OFFSETS = _template()
_GROUPS = {  # which joints' offsets each proportion parameter lengthens
    1: ["left_knee", "right_knee", "left_ankle", "right_ankle", "left_foot", "right_foot"],
    2: ["spine1", "spine2", "spine3", "neck", "head"],
    3: ["left_elbow", "right_elbow", "left_wrist", "right_wrist"],
}
_WIDTHS = {4: ["left_collar", "right_collar", "left_shoulder", "right_shoulder"], 5: ["left_hip", "right_hip"]}
# (SHAPE_DIM, 22, 3): 1 where parameter k scales that offset component. Stature scales every bone
# (the standing height changes by 10 cm per unit); lengths whole offsets; widths their x
_SCALES = torch.zeros(SHAPE_DIM, NUM_JOINTS, 3)
_SCALES[0] = 1.0
for _k, _names in _GROUPS.items():
    _SCALES[_k, [JOINT_INDEX[n] for n in _names]] = 1.0
for _k, _names in _WIDTHS.items():
    _SCALES[_k, [JOINT_INDEX[n] for n in _names], 0] = 1.0


def rest_offsets(shape: torch.Tensor | None = None, dtype=torch.float32) -> torch.Tensor:
    """Bone offsets (..., 22, 3) for body-shape vectors (..., SHAPE_DIM); None -> average body.
    Each parameter k scales the offset components of _SCALES[k] by (1 + STEP_k x_k), stature
    every component: one product over the parameters (runs for every segment the runtime makes)."""
    base = TEMPLATE_OFFSETS.to(dtype)
    if shape is None:
        return base.clone()
    shape = shape.to(dtype)
    if shape.shape[-1] != SHAPE_DIM:
        raise ValueError(f"body shape must have {SHAPE_DIM} components {SHAPE_NAMES}, got {shape.shape[-1]}")
    steps = torch.tensor([STEP[n] for n in SHAPE_NAMES], dtype=dtype)
    factors = 1 + (shape * steps)[..., :, None, None] * _SCALES.to(dtype)  # (..., SHAPE_DIM, 22, 3)
    return base * factors.prod(-3)


def pelvis_height(offsets: torch.Tensor) -> torch.Tensor:
    """Rest height of the pelvis above the ground for offsets (..., 22, 3): the leg's vertical drop
    plus the foot clearance. Used as the 'leg length' by which root trajectories are scaled."""
    leg = offsets[..., [1, 4, 7, 10], 1].sum(-1)  # hip, knee, ankle, foot drops (negative)
    return -leg + FOOT_CLEARANCE


def standing_height(shape: torch.Tensor | None) -> float | torch.Tensor:
    """Approximate stature: pelvis height + spine to head + 0.12 m of skull above the head joint."""
    off = TEMPLATE_OFFSETS if shape is None else rest_offsets(shape, torch.float64)
    h = pelvis_height(off) + off[..., [3, 6, 9, 12, 15], 1].sum(-1) + SKULL
    return float(h) if shape is None else h


# relative change of the lengths each shape parameter scales, per unit; stature scales every
# bone so that the standing height changes by 10 cm (the skull and foot clearance stay)
STEP = {"stature": 0.10 / (standing_height(None) - FOOT_CLEARANCE - SKULL), "leg_length": 0.05, "torso_length": 0.05,
        "arm_length": 0.05, "shoulder_width": 0.08, "hip_width": 0.08}


def rest_positions(offsets: torch.Tensor) -> torch.Tensor:
    """World joint positions (..., 22, 3) of the rest pose standing on the ground."""
    pos = [None] * NUM_JOINTS
    root = torch.zeros_like(offsets[..., 0, :])
    root[..., 1] = pelvis_height(offsets)
    pos[0] = root
    for j in range(1, NUM_JOINTS):
        pos[j] = pos[PARENTS[j]] + offsets[..., j, :]
    return torch.stack(pos, -2)


def random_shapes(n: int, generator: torch.Generator | None = None, scale: float = 1.0) -> torch.Tensor:
    return (torch.randn(n, SHAPE_DIM, generator=generator) * scale).clamp(-2.5, 2.5)


def _jumps(parents: list[int]) -> list[torch.Tensor]:
    """Pointer jumping over the tree, for global rotations in ceil(log2(depth + 1)) batched steps
    (3 for SMPL's depth of 7) instead of one per depth: index n is a virtual identity above the
    root; at each step every joint's rotation relative to its current ancestor is left-multiplied
    by that ancestor's, and the ancestor becomes the ancestor's ancestor. The list holds each
    step's ancestor indices."""
    n = len(parents)
    anc = [p if p >= 0 else n for p in parents] + [n]
    steps = []
    while any(a != n for a in anc):
        steps.append(torch.tensor(anc))
        anc = [anc[a] for a in anc]
    return steps


def _ancestry(parents: list[int]) -> torch.Tensor:
    """(22, 21): entry (j, k - 1) is 1 where joint k is j or on j's way to the root (k > 0), so that
    a joint's position is the root's plus this row times the bone vectors of joints 1..21."""
    A = torch.zeros(len(parents), len(parents) - 1, dtype=torch.float64)
    for j in range(len(parents)):
        k = j
        while k > 0:
            A[j, k - 1] = 1.0
            k = parents[k]
    return A


_JUMPS = _jumps(PARENTS)
_ANCESTRY = _ancestry(PARENTS)
_BONE_PARENTS = torch.tensor(PARENTS[1:])


def forward_kinematics(root_pos: torch.Tensor, root_rot: torch.Tensor, local_rot: torch.Tensor,
                       offsets: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The one FK of the project.

    root_pos (..., 3) pelvis position; root_rot (..., 3, 3) pelvis global rotation;
    local_rot (..., 21, 3, 3) rotations of joints 1..21 relative to their parents;
    offsets (..., 22, 3) or (22, 3) rest bone offsets (broadcast).
    Returns joint positions (..., 22, 3) and global rotations (..., 22, 3, 3).
    Written as few batched operations as it can be (at one avatar each operation costs more to
    dispatch than to compute): global rotations by pointer jumping (_jumps), then every bone
    vector at once and the positions as one product with the ancestry matrix.
    """
    eye = torch.eye(3, dtype=root_rot.dtype).expand(*root_rot.shape[:-2], 1, 3, 3)
    glob = torch.cat((root_rot[..., None, :, :], local_rot, eye), -3)  # relative to the parent
    for anc in _JUMPS:
        glob = glob.index_select(-3, anc) @ glob
    glob = glob[..., :NUM_JOINTS, :, :]
    # each bone vector: its parent's global rotation times the rest offset, written out (a batched
    # 3x3 matmul costs more than its 9 products at these sizes)
    bones = (glob.index_select(-3, _BONE_PARENTS) * offsets.to(root_pos.dtype)[..., 1:, None, :]).sum(-1)
    pos = root_pos[..., None, :] + _ANCESTRY.to(root_pos.dtype) @ bones
    return pos, glob
