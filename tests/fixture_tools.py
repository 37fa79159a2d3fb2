"""Synthetic motion and foreign-skeleton BVH fixtures, written with the project's own writer.

`procedural_walk` makes a walk cycle on the canonical body. `foreign_bvh` re-expresses it on a
skeleton of another naming (LAFAN1, CMU, Mixamo) with its own proportions, its own rest pose
(every joint's rest frame turned by an arbitrary rotation), its own unit, axes and Euler order,
and extra joints the canonical body lacks. Run `python tests/fixture_tools.py` to rewrite
tests/fixtures/*.bvh.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from avatar_motor.body import rotations as rot
from avatar_motor.body.skeleton import JOINT_INDEX, JOINT_NAMES, NUM_JOINTS, PARENTS, forward_kinematics, rest_offsets
from avatar_motor.io.bvh import BVH, bvh_from_rotations, write_bvh

FIXTURES = Path(__file__).parent / "fixtures"


def procedural_walk(frames: int = 60, fps: float = 30.0):
    """Canonical walk: (root_pos (T,3), global rotations (T,22,3,3)) in float64, facing +Z."""
    t = torch.arange(frames, dtype=torch.float64) / fps
    ph = 2 * math.pi * t / 1.1
    local = torch.eye(3, dtype=torch.float64).repeat(frames, 21, 1, 1)

    def setj(name, R):
        local[:, JOINT_INDEX[name] - 1] = R

    def ax(axis, a):
        return rot.euler_to_matrix(torch.stack([a if c == axis else torch.zeros_like(a) for c in "XYZ"], -1), "XYZ")

    setj("left_hip", ax("X", -0.45 * torch.sin(ph)))
    setj("right_hip", ax("X", 0.45 * torch.sin(ph)))
    setj("left_knee", ax("X", 0.35 + 0.3 * torch.cos(ph)))
    setj("right_knee", ax("X", 0.35 - 0.3 * torch.cos(ph)))
    setj("left_shoulder", ax("Z", torch.full_like(t, -1.3)) @ ax("X", 0.3 * torch.sin(ph)))
    setj("right_shoulder", ax("Z", torch.full_like(t, 1.3)) @ ax("X", -0.3 * torch.sin(ph)))
    setj("left_elbow", ax("Y", torch.full_like(t, 0.3)))
    setj("right_elbow", ax("Y", torch.full_like(t, -0.3)))
    setj("spine2", ax("Y", 0.08 * torch.sin(ph)))
    root_rot = ax("Y", 0.05 * torch.sin(ph))
    off = rest_offsets(None, torch.float64)
    # plant the stance foot: move the pelvis so the lower foot does not slide, and keep it on the ground
    J, _ = forward_kinematics(torch.zeros(frames, 3, dtype=torch.float64), root_rot, local, off)
    feet = J[:, [10, 11]]  # toes
    stance = feet[..., 1].argmin(-1)
    st = feet[torch.arange(frames), stance]
    step = torch.zeros(frames, 3, dtype=torch.float64)
    same = stance[1:] == stance[:-1]
    step[1:] = torch.where(same[:, None], -(st[1:] - st[:-1]), torch.zeros(1, 3, dtype=torch.float64))
    root = torch.cumsum(step, 0)
    root[:, 1] = 0.02 - J[..., 1].min(-1).values
    _, G = forward_kinematics(root, root_rot, local, off)
    return root, G


# naming -> (fixture joint name per canonical joint, extra joints inserted as (name, between child), prefix)
SKELETONS = {
    "lafan1": dict(names={"pelvis": "Hips", "spine1": "Spine", "spine2": "Spine1", "spine3": "Spine2", "neck": "Neck",
                          "head": "Head", "left_hip": "LeftUpLeg", "left_knee": "LeftLeg", "left_ankle": "LeftFoot",
                          "left_foot": "LeftToe", "left_collar": "LeftShoulder", "left_shoulder": "LeftArm",
                          "left_elbow": "LeftForeArm", "left_wrist": "LeftHand"},
                   inserts={}, unit=0.01, up="Y", order="ZYX", scale=1.06),
    "cmu": dict(names={"pelvis": "Hips", "spine1": "LowerBack", "spine2": "Spine", "spine3": "Spine1", "neck": "Neck",
                       "head": "Head", "left_hip": "LeftUpLeg", "left_knee": "LeftLeg", "left_ankle": "LeftFoot",
                       "left_foot": "LeftToeBase", "left_collar": "LeftShoulder", "left_shoulder": "LeftArm",
                       "left_elbow": "LeftForeArm", "left_wrist": "LeftHand"},
                inserts={"left_hip": "LHipJoint", "right_hip": "RHipJoint", "head": "Neck1"}, unit=0.0254, up="Y",
                order="ZYX", scale=0.93),
    "mixamo": dict(names={"pelvis": "mixamorig:Hips", "spine1": "mixamorig:Spine", "spine2": "mixamorig:Spine1",
                          "spine3": "mixamorig:Spine2", "neck": "mixamorig:Neck", "head": "mixamorig:Head",
                          "left_hip": "mixamorig:LeftUpLeg", "left_knee": "mixamorig:LeftLeg",
                          "left_ankle": "mixamorig:LeftFoot", "left_foot": "mixamorig:LeftToeBase",
                          "left_collar": "mixamorig:LeftShoulder", "left_shoulder": "mixamorig:LeftArm",
                          "left_elbow": "mixamorig:LeftForeArm", "left_wrist": "mixamorig:LeftHand"},
                   inserts={}, unit=0.01, up="Z", order="XYZ", scale=1.0),
}


def _full_names(spec: dict) -> dict[str, str]:
    out = {}
    for canon in JOINT_NAMES:
        key = canon.replace("right_", "left_")
        n = spec["names"][key]
        if canon.startswith("right_"):
            n = n.replace("Left", "Right")
        out[canon] = n
    return out


def _file_axes(up: str) -> np.ndarray:
    """A with rows = world X (left), Y (up), Z (fwd) expressed in file axes."""
    if up == "Y":
        return np.eye(3)
    return np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])  # Z-up file: world up = file Z


def foreign_bvh(naming: str, frames: int = 60, seed: int = 0) -> BVH:
    spec = SKELETONS[naming]
    names = _full_names(spec)
    g = torch.Generator().manual_seed(seed)
    root, G_can = procedural_walk(frames)
    off_can = rest_offsets(None, torch.float64)
    # every canonical joint's fixture frame is turned by Q_j: a different rest pose and bone frames
    Q = rot.axis_angle_to_matrix((torch.rand(NUM_JOINTS, 3, generator=g, dtype=torch.float64) - 0.5) * 1.2)
    s = spec["scale"]
    # build the fixture hierarchy (world axes), inserting extra joints halfway along a bone
    fx_names, fx_parents, fx_off, fx_G = [], [], [], []
    index = {}
    for j, canon in enumerate(JOINT_NAMES):
        p = PARENTS[j]
        o = s * (Q[p] @ off_can[j]) if p >= 0 else torch.zeros(3, dtype=torch.float64)
        parent_fx = index[JOINT_NAMES[p]] if p >= 0 else -1
        if canon in spec["inserts"]:
            fx_names.append(spec["inserts"][canon])
            fx_parents.append(parent_fx)
            fx_off.append(o / 2)
            fx_G.append(G_can[:, p] @ Q[p].T)
            parent_fx, o = len(fx_names) - 1, o / 2
        index[canon] = len(fx_names)
        fx_names.append(names[canon])
        fx_parents.append(parent_fx)
        fx_off.append(o)
        fx_G.append(G_can[:, j] @ Q[j].T)
    leaf = {"head": (0, 0.1, 0), "left_wrist": (0.08, 0, 0), "right_wrist": (-0.08, 0, 0), "left_foot": (0, 0, 0.05), "right_foot": (0, 0, 0.05)}
    ends = {index[n]: (s * (Q[JOINT_INDEX[n]] @ torch.tensor(v, dtype=torch.float64))) for n, v in leaf.items()}
    # into file axes and units
    A = torch.from_numpy(_file_axes(spec["up"]))
    At = A.T
    u = spec["unit"]
    G_file = torch.stack([At @ Gw @ A for Gw in fx_G], 1)  # (T, J, 3, 3)
    local = G_file.clone()
    for k, p in enumerate(fx_parents):
        if p >= 0:
            local[:, k] = G_file[:, p].transpose(-1, -2) @ G_file[:, k]
    off_file = np.stack([(At @ o).numpy() / u for o in fx_off])
    ends_file = {k: (At @ v).numpy() / u for k, v in ends.items()}
    root_file = (root * s) @ A / u  # row vectors: (A^T p)^T = p^T A
    return bvh_from_rotations(fx_names, fx_parents, off_file, root_file.numpy(), local, 1 / 30.0, spec["order"], ends_file)


def write_fixtures() -> list[Path]:
    FIXTURES.mkdir(exist_ok=True)
    out = []
    for naming in SKELETONS:
        p = FIXTURES / f"walk_{naming}.bvh"
        write_bvh(p, foreign_bvh(naming), precision=5)
        out.append(p)
    return out


if __name__ == "__main__":
    for p in write_fixtures():
        print(p)
