"""Reader for DeepMimic's humanoid motion files (the `humanoid3d_*.txt` clips of the DeepMimic
project, also distributed with pybullet under `pybullet_data/data/motions/`).

Format: JSON `{"Loop": "wrap" | "none", "Frames": [[...], ...]}`; each frame has 44 values:
the frame's duration (seconds to the next frame; the last frame's is 0), the root position (3),
then per joint a quaternion (w, x, y, z) or, for the 1-DoF knees and elbows, one angle in
radians about the joint's z axis, in the order of `LAYOUT`. World and joint frames: y up, the
character faces +x with its right side toward +z, metres.

The clip is read into a `BVH` of the humanoid's skeleton (the offsets of DeepMimic's
`humanoid3d` character; pybullet's `humanoid.urdf` is the same body scaled by 4), so the one
retargeter takes it like any other file (naming "deepmimic" in data/retarget.py). The humanoid
has one chest joint, no collars, toes or head joint: fixed joints are added where our body has
joints (a head above the neck, collars between chest and shoulders, toes at the front of the
foot box), so that every canonical bone has a direction; they carry no motion of their own.
Frames of unequal duration are resampled to the clip's most common frame time.
"""
from __future__ import annotations

import json
import math

import numpy as np
import torch

from ..body import rotations as rot
from ..body.skeleton import FOOT_CLEARANCE
from .bvh import MAX_BYTES, MIN_FRAME_TIME, MAX_FRAME_TIME, BVH, BVHError, bvh_from_rotations

# (joint, channel kind) in the file's order after duration and root position; "quat" = w, x, y, z,
# "z" = one angle about the joint's z axis (DeepMimic's revolute knees and elbows); DeepMimic's
# root is our skeleton's pelvis (PELVIS)
LAYOUT = (("pelvis", "quat"), ("chest", "quat"), ("neck", "quat"),
          ("right_hip", "quat"), ("right_knee", "z"), ("right_ankle", "quat"),
          ("right_shoulder", "quat"), ("right_elbow", "z"),
          ("left_hip", "quat"), ("left_knee", "z"), ("left_ankle", "quat"),
          ("left_shoulder", "quat"), ("left_elbow", "z"))
FRAME_VALUES = 1 + 3 + sum(4 if kind == "quat" else 1 for _, kind in LAYOUT)  # 44


# The skeleton's root is placed where our pelvis joint sits, PELVIS above DeepMimic's root (which
# lies between the hip joints) and turned with it. Our pelvis is 8.5 cm above the hips: mapped to
# DeepMimic's root, a standing body would sink by that much and a lying one would not, so no one
# lift onto the ground would fit both.
PELVIS = (0.015, 0.085, 0.0)


def _side(z: float) -> list[tuple[str, str, tuple[float, float, float]]]:
    s = "right" if z > 0 else "left"
    return [(f"{s}_hip", "pelvis", (-PELVIS[0], -PELVIS[1], 0.084887 * z)),
            (f"{s}_knee", f"{s}_hip", (0.0, -0.421546, 0.0)),
            (f"{s}_ankle", f"{s}_knee", (0.0, -0.40987, 0.0)),
            # fixed: the ball of the foot, near the front of DeepMimic's foot box (centre (0.045,
            # -0.0225, 0), size 0.177 x 0.055 x 0.09 from the ankle: sole 0.05 below the ankle),
            # FOOT_CLEARANCE above the sole like our toe joint
            (f"{s}_toe", f"{s}_ankle", (0.12, -0.05 + FOOT_CLEARANCE, 0.0)),
            # fixed: a collar on the chest, a third of the way to the shoulder
            (f"{s}_collar", "chest", (-0.02405, 0.2235, 0.06 * z)),
            (f"{s}_shoulder", f"{s}_collar", (0.0, 0.02, 0.12311 * z)),
            (f"{s}_elbow", f"{s}_shoulder", (0.0, -0.274788, 0.0)),
            (f"{s}_wrist", f"{s}_elbow", (0.0, -0.258947, 0.0))]  # fixed in DeepMimic too


# joint, parent, offset from the parent (metres, rest pose: every rotation zero)
SKELETON = [("pelvis", "", (0.0, 0.0, 0.0)),
            ("chest", "pelvis", (-PELVIS[0], 0.236151 - PELVIS[1], 0.0)),
            ("neck", "chest", (0.0, 0.223894, 0.0)),
            ("head", "neck", (0.0, 0.12, 0.0)),  # fixed: inside the head sphere (centre 0.175 above the neck)
            *_side(1.0), *_side(-1.0)]
_END_SITES = {"head": (0.0, 0.16, 0.0), "right_toe": (0.05, 0.0, 0.0), "left_toe": (0.05, 0.0, 0.0),
              "right_wrist": (0.0, -0.08, 0.0), "left_wrist": (0.0, -0.08, 0.0)}


# world axes (rows: our left, up, forward) in DeepMimic's: it faces +x with its right toward +z
AXES = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])


class DeepMimicError(BVHError):
    """A DeepMimic motion file could not be read; the message names the file, the problem and the fix."""


def looks_like_deepmimic(data: bytes) -> bool:
    """A JSON object (DeepMimic's files are), not a BVH (which starts with HIERARCHY)."""
    return data[:64].lstrip().startswith(b"{")


def _fail(src: str, problem: str, fix: str) -> DeepMimicError:
    return DeepMimicError(f"{src}: {problem}. {fix}")


def parse_frames(data: bytes, src: str) -> np.ndarray:
    """(F, 44) float64 frames, validated. (The file's loop mode is not needed: a clip is imported
    once, as it is.)"""
    if len(data) > MAX_BYTES:
        raise _fail(src, f"is larger than {MAX_BYTES >> 20} MB", "Split the clip")
    try:
        doc = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise _fail(src, f"is not valid JSON ({e})", "Pass a DeepMimic motion file (a JSON object with a Frames list)") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("Frames"), list):
        raise _fail(src, "has no 'Frames' list", "Pass a DeepMimic motion file: {\"Loop\": ..., \"Frames\": [[duration, ...], ...]}")
    frames = doc["Frames"]
    if len(frames) < 2:
        raise _fail(src, f"has {len(frames)} frame(s)", "A clip needs at least 2 frames")
    for i, f in enumerate(frames):
        if not isinstance(f, list) or len(f) != FRAME_VALUES:
            n = len(f) if isinstance(f, list) else type(f).__name__
            raise _fail(src, f"frame {i} has {n} values, a humanoid3d frame has {FRAME_VALUES} (duration, root position, "
                        "8 quaternions, 4 knee and elbow angles)", "This file is for another DeepMimic character; "
                        "only the humanoid3d clips can be imported")
    try:
        F = np.asarray(frames, np.float64)
    except (TypeError, ValueError):
        raise _fail(src, "has a frame value that is not a number", "Fix or re-export the clip") from None
    if not np.isfinite(F).all():
        i = int(np.argwhere(~np.isfinite(F))[0, 0])
        raise _fail(src, f"frame {i} has a NaN or infinite value", "Fix or re-export the clip")
    dur = F[:-1, 0]
    if (dur < MIN_FRAME_TIME).any() or (dur > MAX_FRAME_TIME).any():
        i = int(np.argmax((dur < MIN_FRAME_TIME) | (dur > MAX_FRAME_TIME)))
        raise _fail(src, f"frame {i} lasts {dur[i]:g} s", f"Each frame but the last must last {MIN_FRAME_TIME:g}-{MAX_FRAME_TIME:g} s")
    col = 4
    for name, kind in LAYOUT:
        if kind == "quat":
            n = np.linalg.norm(F[:, col:col + 4], axis=1)
            if (n < 0.5).any() or (n > 2.0).any():
                i = int(np.argmax((n < 0.5) | (n > 2.0)))
                raise _fail(src, f"frame {i}: the {name} quaternion has norm {n[i]:.3g}, not 1",
                            "Fix the clip (quaternions are w, x, y, z)")
            col += 4
        else:
            col += 1
    return F


def _uniform(F: np.ndarray) -> tuple[np.ndarray, float]:
    """The frames at one frame time: as they are when their durations agree (within 1 %), else
    resampled at the most common duration (linear positions and angles, slerped quaternions)."""
    dur = F[:-1, 0]
    key = np.round(dur, 4)
    vals, counts = np.unique(key, return_counts=True)
    dt = float(np.median(dur[key == vals[np.argmax(counts)]]))
    if np.abs(dur - dt).max() <= 0.01 * dt:
        return F, dt
    t = np.concatenate(([0.0], np.cumsum(dur)))
    n = int(math.floor(t[-1] / dt + 1e-6)) + 1
    tn = np.arange(n) * dt
    i0 = np.clip(np.searchsorted(t, tn, side="right") - 1, 0, len(F) - 2)
    w = np.clip((tn - t[i0]) / (t[i0 + 1] - t[i0]), 0.0, 1.0)
    out = F[i0] * (1 - w[:, None]) + F[i0 + 1] * w[:, None]  # positions, angles; quaternions below
    col = 4
    wt = torch.from_numpy(w)
    for _, kind in LAYOUT:
        if kind == "quat":
            qa, qb = (torch.from_numpy(F[k, col:col + 4]) for k in (i0, i0 + 1))
            out[:, col:col + 4] = rot.quat_slerp(rot.normalize(qa), rot.normalize(qb), wt).numpy()
            col += 4
        else:
            col += 1
    out[:, 0] = dt
    return out, dt


def read_deepmimic(data: bytes, name: str = "<bytes>") -> BVH:
    """A DeepMimic humanoid3d clip as a BVH on the humanoid's skeleton (module docstring)."""
    F, dt = _uniform(parse_frames(data, name))
    names = [n for n, _, _ in SKELETON]
    index = {n: i for i, n in enumerate(names)}
    parents = [index[p] if p else -1 for _, p, _ in SKELETON]
    offsets = np.array([o for _, _, o in SKELETON], np.float64)
    local = torch.eye(3, dtype=torch.float64).repeat(len(F), len(names), 1, 1)
    col = 4
    for joint, kind in LAYOUT:
        if kind == "quat":
            local[:, index[joint]] = rot.quat_to_matrix(torch.from_numpy(F[:, col:col + 4]))
            col += 4
        else:
            ang = torch.from_numpy(F[:, col])
            local[:, index[joint]] = rot.axis_angle_to_matrix(torch.stack((0 * ang, 0 * ang, ang), -1))
            col += 1
    pelvis = F[:, 1:4] + (local[:, 0] @ torch.tensor(PELVIS, dtype=torch.float64)).numpy()
    b = bvh_from_rotations(names, parents, offsets, pelvis, local, dt, order="ZYX",
                           end_sites={index[n]: np.array(v) for n, v in _END_SITES.items()})
    b.source = name
    return b
