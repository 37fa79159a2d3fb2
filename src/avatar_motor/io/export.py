"""Exporters for motion on the canonical body: BVH (canonical skeleton, real offsets, centimetres,
re-imports exactly), AMASS-style npz (the motion state plus named arrays), glTF binary (see
io/gltf.py) and FBX (through Blender, io/fbx.py). Joints are named in the convention asked for
(io/skeletons.py). All write through a temporary file and a rename.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from ..body import rotations as rot
from ..body.skeleton import JOINT_NAMES, NUM_JOINTS, PARENTS, SHAPE_NAMES, rest_offsets
from ..body.motion_state import FPS, unpack
from .atomic import write_file
from .bvh import bvh_from_rotations, write_bvh
from .skeletons import joint_names

BVH_SCALE = 100.0  # metres -> centimetres, what BVH viewers expect
LEAF_END_SITES = {"head": (0.0, 0.10, 0.0), "left_wrist": (0.08, 0.0, 0.0), "right_wrist": (-0.08, 0.0, 0.0),
                  "left_foot": (0.0, 0.0, 0.05), "right_foot": (0.0, 0.0, 0.05)}


def canonical_bvh(states: torch.Tensor, shape: torch.Tensor | None = None, fps: float = FPS, skeleton: str = "smpl"):
    """A BVH object of the canonical skeleton from world states (T, 267), its joints named in the
    `skeleton` convention."""
    u = unpack(states.double())
    local = u.rotations  # (T, 22, 3, 3)
    off = rest_offsets(shape, torch.float64).numpy() * BVH_SCALE
    ends = {JOINT_NAMES.index(n): np.array(v) * BVH_SCALE for n, v in LEAF_END_SITES.items()}
    return bvh_from_rotations(joint_names(skeleton), PARENTS, off, u.root_pos.numpy() * BVH_SCALE, local, 1.0 / fps, "ZXY",
                              ends)


MOTION_FORMATS = (".bvh", ".glb", ".npz", ".fbx")
FORMATS_TEXT = ", ".join(MOTION_FORMATS[:-1]) + " or " + MOTION_FORMATS[-1]  # for error messages


def write_motion(path: str | Path, states: torch.Tensor, shape: torch.Tensor | None = None, fps: float = FPS,
                 meta: dict | None = None, skeleton: str = "smpl") -> Path:
    """Write world states (T, 267) as .bvh, .glb, .npz or .fbx, chosen by the suffix, the joints
    named in the `skeleton` convention (io/skeletons.py)."""
    path = Path(path)
    suffix = path.suffix.lower()
    names = joint_names(skeleton)  # an unknown convention is refused before anything is written
    if suffix == ".bvh":
        b = canonical_bvh(states, shape, fps, skeleton)
        write_file(path, lambda tmp: write_bvh(tmp, b))
    elif suffix == ".fbx":
        from .fbx import bvh_to_fbx
        b = canonical_bvh(states, shape, fps, skeleton)
        write_file(path, lambda tmp: bvh_to_fbx(b, tmp))
    elif suffix == ".npz":
        u = unpack(states.double())
        arrays = {
            "states": states.float().numpy(), "fps": np.float32(fps),
            "root_pos": u.root_pos.float().numpy(),
            "root_orient": rot.matrix_to_axis_angle(u.root_rot).float().numpy(),
            "pose_body": rot.matrix_to_axis_angle(u.local_rot).reshape(len(states), -1).float().numpy(),
            "joints": u.joints.float().numpy(), "velocities": u.velocities.float().numpy(),
            "betas": (shape if shape is not None else torch.zeros(len(SHAPE_NAMES))).float().numpy(),
            "joint_names": np.array(names), "shape_names": np.array(SHAPE_NAMES),
            "meta": np.array(json.dumps(meta or {})),
        }

        def w(tmp):
            with open(tmp, "wb") as f:
                np.savez(f, **arrays)
        write_file(path, w)
    elif suffix in (".glb", ".gltf"):
        from .gltf import write_glb
        if suffix == ".gltf":
            raise ValueError(f"{path}: write glTF binary (.glb), which holds the body and its animation in one file")
        write_file(path, lambda tmp: write_glb(tmp, states, shape, fps, names))
    else:
        raise ValueError(f"{path}: unknown motion format {suffix!r}; use {FORMATS_TEXT}")
    return path


def read_npz_states(path: str | Path) -> tuple[torch.Tensor, float, torch.Tensor]:
    """(states (T, 267), fps, body shape (SHAPE_DIM,)) of an npz this project wrote."""
    with np.load(path, allow_pickle=False) as z:
        if "states" not in z:
            raise ValueError(f"{path}: no 'states' array; this npz was not written by avatar-motor")
        betas = z["betas"] if "betas" in z else np.zeros(len(SHAPE_NAMES))
        return torch.from_numpy(z["states"]).float(), float(z["fps"]), torch.from_numpy(betas).float()


assert NUM_JOINTS == len(JOINT_NAMES)
