"""Synthetic motion and foreign-skeleton BVH fixtures, written with the project's own writer.

`procedural_walk` makes a walk cycle on the canonical body. `foreign_bvh` re-expresses it on a
skeleton of another naming (LAFAN1, CMU, Mixamo) with its own proportions, its own rest pose
(every joint's rest frame turned by an arbitrary rotation), its own unit, axes and Euler order,
and extra joints the canonical body lacks. Run `python tests/fixture_tools.py` to rewrite
tests/fixtures/*.bvh.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

from avatar_motor.body import rotations as rot
from avatar_motor.body.skeleton import JOINT_INDEX, JOINT_NAMES, NUM_JOINTS, PARENTS, forward_kinematics, rest_offsets
from avatar_motor.io.bvh import BVH, bvh_from_rotations, write_bvh

FIXTURES = Path(__file__).parent / "fixtures"


def _axis(axis: str, a: torch.Tensor) -> torch.Tensor:
    return rot.euler_to_matrix(torch.stack([a if c == axis else torch.zeros_like(a) for c in "XYZ"], -1), "XYZ")


def _planted(local: torch.Tensor, root_rot: torch.Tensor):
    """Root motion for a pose sequence: the pelvis moves so the lower foot does not slide, and
    the lowest joint stays at 2 cm. Returns (root_pos (T,3), global rotations (T,22,3,3))."""
    frames = local.shape[0]
    off = rest_offsets(None, torch.float64)
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


def procedural_walk(frames: int = 60, fps: float = 30.0):
    """Canonical walk: (root_pos (T,3), global rotations (T,22,3,3)) in float64, facing +Z."""
    t = torch.arange(frames, dtype=torch.float64) / fps
    ph = 2 * math.pi * t / 1.1
    local = torch.eye(3, dtype=torch.float64).repeat(frames, 21, 1, 1)

    def setj(name, R):
        local[:, JOINT_INDEX[name] - 1] = R

    ax = _axis
    setj("left_hip", ax("X", -0.45 * torch.sin(ph)))
    setj("right_hip", ax("X", 0.45 * torch.sin(ph)))
    setj("left_knee", ax("X", 0.35 + 0.3 * torch.cos(ph)))
    setj("right_knee", ax("X", 0.35 - 0.3 * torch.cos(ph)))
    setj("left_shoulder", ax("Z", torch.full_like(t, -1.3)) @ ax("X", 0.3 * torch.sin(ph)))
    setj("right_shoulder", ax("Z", torch.full_like(t, 1.3)) @ ax("X", -0.3 * torch.sin(ph)))
    setj("left_elbow", ax("Y", torch.full_like(t, 0.3)))
    setj("right_elbow", ax("Y", torch.full_like(t, -0.3)))
    setj("spine2", ax("Y", 0.08 * torch.sin(ph)))
    return _planted(local, ax("Y", 0.05 * torch.sin(ph)))


def _ramp(t: torch.Tensor, a: float, b: float) -> torch.Tensor:
    """0 before a, 1 after b, a cosine in between."""
    x = ((t - a) / (b - a)).clamp(0, 1)
    return 0.5 - 0.5 * torch.cos(math.pi * x)


# the phases of procedural_mix, seconds: standing, a crouch down and up, then walking
MIX_PHASES = {"standing": 0.3, "crouching": 1.0, "mid-stride": 2.4, "walking": 2.9}


def procedural_mix(seconds: float = 3.5, fps: float = 30.0):
    """Canonical motion of several kinds, for starting frames of every sort: 0.5 s standing with
    a slight sway, a crouch down to a deep squat and up (0.5-1.5 s), then a walk that starts at
    1.5 s. (root_pos (T,3), global rotations (T,22,3,3)), float64, facing +Z."""
    frames = int(round(seconds * fps))
    t = torch.arange(frames, dtype=torch.float64) / fps
    c = 1.1 * (_ramp(t, 0.5, 1.0) - _ramp(t, 1.0, 1.5))  # crouch depth (hip flexion, rad)
    w = _ramp(t, 1.5, 1.9)  # walk amplitude
    ph = 2 * math.pi * (t - 1.5) / 1.1
    local = torch.eye(3, dtype=torch.float64).repeat(frames, 21, 1, 1)

    def setj(name, R):
        local[:, JOINT_INDEX[name] - 1] = R

    ax = _axis
    for side, sgn in (("left", 1.0), ("right", -1.0)):
        setj(f"{side}_hip", ax("X", -c - sgn * 0.45 * w * torch.sin(ph)))
        setj(f"{side}_knee", ax("X", 2 * c + w * (0.35 + sgn * 0.3 * torch.cos(ph))))
        setj(f"{side}_ankle", ax("X", -c))  # the foot stays flat in the squat
        setj(f"{side}_shoulder", ax("Z", torch.full_like(t, -1.3 * sgn)) @ ax("X", sgn * 0.3 * w * torch.sin(ph) - 0.5 * c))
        setj(f"{side}_elbow", ax("Y", torch.full_like(t, 0.3 * sgn)))
    setj("spine1", ax("X", 0.45 * c))  # lean forward to balance the squat
    setj("spine2", ax("Y", 0.08 * w * torch.sin(ph)) @ ax("Z", 0.03 * torch.sin(2 * math.pi * t / 2.0)))
    return _planted(local, ax("Y", 0.05 * w * torch.sin(ph)))


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
            n = n.replace("Left", "Right") if "Left" in n else n[:-2] + "_r"  # UE: thigh_l -> thigh_r
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


# Real-world quirks, each on procedural_mix: joints that sit on their parents (zero-length
# bones), extra joints along bones, fingers, twist and prop joints to ignore, a ground-level root
# above the pelvis, other frame rates and units. "zero": canonical joints placed on their parent's
# location (their own bone is taken up by their children); "inserts": extra joints on the bone
# that ends at a canonical joint, at a fraction of its length (0 = on the parent); "extras":
# (name, fixture parent, canonical joint whose frame the offset is in, offset m, End Site m or None).
def _hand(side: str, sgn: float, names: list[tuple[str, str, tuple, tuple | None]], parent: str):
    return [(n.format(s=side), (p or parent).format(s=side), f"{'left' if sgn > 0 else 'right'}_wrist",
             (sgn * o[0], o[1], o[2]), None if e is None else (sgn * e[0], e[1], e[2])) for n, p, o, e in names]


_UE5_FINGERS = [("thumb_01_{s}", None, (0.02, -0.01, 0.03), (0.02, 0.0, 0.03)),
                ("index_metacarpal_{s}", None, (0.03, 0.0, 0.015), None), ("index_01_{s}", "index_metacarpal_{s}", (0.05, 0.0, 0.0), (0.04, 0, 0)),
                ("middle_metacarpal_{s}", None, (0.03, 0.0, 0.0), None), ("middle_01_{s}", "middle_metacarpal_{s}", (0.05, 0.0, 0.0), (0.045, 0, 0)),
                ("ring_metacarpal_{s}", None, (0.03, 0.0, -0.012), None), ("ring_01_{s}", "ring_metacarpal_{s}", (0.05, 0.0, -0.003), (0.04, 0, 0)),
                ("pinky_metacarpal_{s}", None, (0.028, 0.0, -0.024), None), ("pinky_01_{s}", "pinky_metacarpal_{s}", (0.045, 0.0, -0.006), (0.03, 0, 0))]
_MIXAMO_FINGERS = [(f"mixamorig:{{s}}Hand{f}{k}", None if k == 1 else f"mixamorig:{{s}}Hand{f}{k - 1}", o if k == 1 else d, d if k == 3 else None)
                   for f, o, d in (("Thumb", (0.02, -0.01, 0.025), (0.02, 0.0, 0.015)), ("Index", (0.08, 0.0, 0.015), (0.025, 0, 0)),
                                   ("Middle", (0.08, 0.0, 0.0), (0.027, 0, 0)), ("Ring", (0.075, 0.0, -0.012), (0.024, 0, 0)),
                                   ("Pinky", (0.07, 0.0, -0.024), (0.02, 0, 0))) for k in (1, 2, 3)]
QUIRKS = {
    # the CMU database's common BVH conversion: Hips -> LHipJoint/RHipJoint/LowerBack on the hips,
    # Neck and LeftShoulder on Spine1, Neck1 between Neck and Head, LeftFingerBase and LThumb on
    # the hand, 120 fps
    "cmu_real": dict(
        names={"pelvis": "Hips", "spine1": "LowerBack", "spine2": "Spine", "spine3": "Spine1", "neck": "Neck", "head": "Head",
               "left_hip": "LeftUpLeg", "left_knee": "LeftLeg", "left_ankle": "LeftFoot", "left_foot": "LeftToeBase",
               "left_collar": "LeftShoulder", "left_shoulder": "LeftArm", "left_elbow": "LeftForeArm", "left_wrist": "LeftHand"},
        zero=("spine1", "neck", "left_collar", "right_collar"),
        inserts={"left_hip": ("LHipJoint", 0.0), "right_hip": ("RHipJoint", 0.0), "head": ("Neck1", 0.5)},
        extras=[x for side, sgn in (("Left", 1.0), ("Right", -1.0)) for x in _hand(side, sgn, [
            ("{s}FingerBase", None, (0.0, 0.0, 0.0), None), ("{s}HandIndex1", "{s}FingerBase", (0.06, 0.0, 0.0), (0.04, 0.0, 0.0))], "{s}Hand")]
        + [("LThumb", "LeftHand", "left_wrist", (0.0, 0.0, 0.0), (0.025, 0.0, 0.025)),
           ("RThumb", "RightHand", "right_wrist", (0.0, 0.0, 0.0), (-0.025, 0.0, 0.025))],
        unit=0.0254, up="Y", order="ZYX", scale=0.97, fps=120.0),
    # Unreal Engine 5 mannequin: a ground-level root, five spine and two neck joints, twist
    # joints, fingers and IK props, Z up, centimetres
    "ue5": dict(
        names={"pelvis": "pelvis", "spine1": "spine_01", "spine2": "spine_03", "spine3": "spine_05", "neck": "neck_01", "head": "head",
               "left_hip": "thigh_l", "left_knee": "calf_l", "left_ankle": "foot_l", "left_foot": "ball_l",
               "left_collar": "clavicle_l", "left_shoulder": "upperarm_l", "left_elbow": "lowerarm_l", "left_wrist": "hand_l"},
        zero=(), root="root",
        inserts={"spine2": ("spine_02", 0.5), "spine3": ("spine_04", 0.5), "head": ("neck_02", 0.5)},
        extras=[x for side, sgn in (("l", 1.0), ("r", -1.0)) for x in _hand(side, sgn, _UE5_FINGERS, "hand_{s}")]
        + [(f"{b}_twist_01_{s}", f"{b}_{s}", f"{side}_{c}", v, None)
           for s, side, sgn in (("l", "left", 1.0), ("r", "right", -1.0))
           for b, c, v in (("upperarm", "shoulder", (sgn * 0.12, 0.0, 0.0)), ("lowerarm", "elbow", (sgn * 0.13, 0.0, 0.0)),
                           ("thigh", "hip", (0.0, -0.2, 0.0)), ("calf", "knee", (0.0, -0.2, 0.0)))]
        + [("ik_foot_root", "root", None, (0.0, 0.0, 0.0), None), ("ik_foot_l", "ik_foot_root", None, (0.1, 0.1, 0.0), (0, 0, 0.05)),
           ("ik_foot_r", "ik_foot_root", None, (-0.1, 0.1, 0.0), (0, 0, 0.05)), ("weapon_r", "hand_r", "right_wrist", (-0.05, 0.0, 0.05), (0, 0, 0.3))],
        unit=0.01, up="Z", order="XYZ", scale=1.04, fps=30.0),
    # Mixamo with three-joint fingers, the mixamorig: prefix, HeadTop_End and toe ends, Z up
    "mixamo_fingers": dict(
        names={k: v for k, v in SKELETONS["mixamo"]["names"].items()},
        zero=(), inserts={},
        extras=[x for side, sgn in (("Left", 1.0), ("Right", -1.0)) for x in _hand(side, sgn, _MIXAMO_FINGERS, "mixamorig:{s}Hand")]
        + [("mixamorig:HeadTop_End", "mixamorig:Head", "head", (0.0, 0.17, 0.02), None)]
        + [(f"mixamorig:{S}Toe_End", f"mixamorig:{S}ToeBase", f"{s}_foot", (0.0, 0.0, 0.05), None) for S, s in (("Left", "left"), ("Right", "right"))],
        unit=0.01, up="Z", order="ZXY", scale=0.96, fps=30.0),
}


def quirky_bvh(naming: str, seconds: float = 3.5, seed: int = 0) -> BVH:
    """procedural_mix written on the QUIRKS skeleton `naming` with our own writer."""
    spec = QUIRKS[naming]
    names = _full_names(spec)
    fps = spec["fps"]
    g = torch.Generator().manual_seed(seed)
    root, G_can = procedural_mix(seconds, fps)
    T = root.shape[0]
    s = spec["scale"]
    off_can = rest_offsets(None, torch.float64)
    P_can, _ = forward_kinematics(root, G_can[:, 0], torch.stack([G_can[:, PARENTS[k]].transpose(-1, -2) @ G_can[:, k]
                                                                  for k in range(1, NUM_JOINTS)], 1), off_can)
    P_can = P_can * s
    turn = lambda: rot.axis_angle_to_matrix((torch.rand(3, generator=g, dtype=torch.float64) - 0.5) * 1.2)  # noqa: E731
    fx = []  # (name, parent fixture index, world positions (T,3), world rotations (T,3,3))
    index: dict[str, int] = {}

    def add(name, parent, P, G):
        index[name] = len(fx)
        fx.append((name, parent, P, G))

    eye = torch.eye(3, dtype=torch.float64).expand(T, 3, 3)
    if spec.get("root"):  # a joint on the ground under the pelvis, turned with nothing
        add(spec["root"], -1, P_can[:, 0] * torch.tensor([1.0, 0.0, 1.0], dtype=torch.float64), eye)
    for j, canon in enumerate(JOINT_NAMES):
        p = PARENTS[j]
        parent_fx = index[names[JOINT_NAMES[p]]] if p >= 0 else (index[spec["root"]] if spec.get("root") else -1)
        if canon in spec["inserts"]:
            ins, frac = spec["inserts"][canon]
            add(ins, parent_fx, P_can[:, p] + frac * (P_can[:, j] - P_can[:, p]), G_can[:, p] @ turn().T)
            parent_fx = index[ins]
        P = P_can[:, p] if canon in spec["zero"] else P_can[:, j]
        add(names[canon], parent_fx, P, G_can[:, j] @ turn().T)
    ends = {}
    for name, parent, canon, v, end in spec["extras"]:
        G_anchor = G_can[:, JOINT_INDEX[canon]] if canon else eye
        P = fx[index[parent]][2] + s * (G_anchor @ torch.tensor(v, dtype=torch.float64))
        add(name, index[parent], P, G_anchor @ turn().T)
        if end is not None:
            ends[index[name]] = s * (fx[-1][3][0].T @ G_anchor[0]) @ torch.tensor(end, dtype=torch.float64)
    leaf = {"head": (0, 0.1, 0), "left_wrist": (0.08, 0, 0), "right_wrist": (-0.08, 0, 0), "left_foot": (0, 0, 0.05), "right_foot": (0, 0, 0.05)}
    has_kids = {p for _, p, _, _ in fx}
    for n, v in leaf.items():
        k = index[names[n]]
        if k not in has_kids:
            ends[k] = s * (fx[k][3][0].T @ G_can[0, JOINT_INDEX[n]]) @ torch.tensor(v, dtype=torch.float64)
    # into file axes and units; offsets from the first frame, where the motion stands in its rest
    # proportions (below a joint that sits on its parent the later frames follow the file's own
    # rotations: that lower back turns at the hips, not 11 cm above them like ours)
    A = torch.from_numpy(_file_axes(spec["up"]))
    u = spec["unit"]
    parents = [p for _, p, _, _ in fx]
    G_file = torch.stack([A.T @ G @ A for _, _, _, G in fx], 1)
    P_file = torch.stack([P @ A for _, _, P, _ in fx], 1) / u  # row vectors: (A^T p)^T = p^T A
    local = G_file.clone()
    trans = torch.zeros_like(P_file)
    for k, p in enumerate(parents):
        if p >= 0:
            local[:, k] = G_file[:, p].transpose(-1, -2) @ G_file[:, k]
            trans[:, k] = (G_file[:, p].transpose(-1, -2) @ (P_file[:, k] - P_file[:, p])[..., None])[..., 0]
    pelvis = index[names["pelvis"]]
    positions = {pelvis: trans[:, pelvis].numpy()} if parents[pelvis] >= 0 else {}
    ends_file = {k: (A.T @ v).numpy() / u for k, v in ends.items()}
    return bvh_from_rotations([n for n, _, _, _ in fx], parents, trans[0].numpy(), P_file[:, 0].numpy(), local, 1 / fps,
                              spec["order"], ends_file, positions)



def deepmimic_clip(frames: int = 45, dt: float = 1 / 30, lying: bool = False, durations: list[float] | None = None) -> tuple[bytes, dict]:
    """A DeepMimic humanoid3d clip (JSON bytes) of our own: a right kick while the root walks
    ahead and turns, the left elbow bending; or, lying, the same on a body lying on its back.
    Returns the bytes and the rotations that went in (root, right hip, right knee angle, left
    elbow angle, per frame), for tests that check where the bones point."""
    t = torch.arange(frames, dtype=torch.float64) * dt
    s = torch.sin(math.pi * t / (frames * dt))  # 0 -> 1 -> 0 over the clip
    yaw = 0.4 * t  # about DeepMimic's up (+y)
    root = rot.axis_angle_to_matrix(torch.stack((0 * t, yaw, 0 * t), -1))
    if lying:  # on its back: pitched 90 degrees about its right-pointing z axis, face up
        root = root @ rot.axis_angle_to_matrix(torch.tensor([0.0, 0.0, math.pi / 2], dtype=torch.float64))
    hip = rot.axis_angle_to_matrix(torch.stack((0.1 * s, 0 * t, 1.4 * s), -1))  # flexion about +z swings the leg forward
    knee = 0 * t if lying else -1.2 * (1 - s)  # the shin extends into the kick (lying: straight, not into the floor)
    elbow = 1.5 * s
    pos = torch.stack((0.3 * t, torch.full_like(t, 0.12 if lying else 0.88), 0 * t), -1)
    one = torch.tensor([1.0, 0, 0, 0], dtype=torch.float64).expand(frames, 4)
    q = rot.matrix_to_quat
    dur = torch.full((frames,), dt, dtype=torch.float64) if durations is None else torch.tensor(durations, dtype=torch.float64)
    dur[-1] = 0.0
    cols = [dur[:, None], pos, q(root), one, one, q(hip), knee[:, None], one, one, torch.zeros(frames, 1, dtype=torch.float64),
            one, torch.zeros(frames, 1, dtype=torch.float64), one, one, elbow[:, None]]
    F = torch.cat(cols, 1)
    doc = {"Loop": "none", "Frames": [[round(v, 6) for v in row] for row in F.tolist()]}
    return json.dumps(doc).encode(), {"root": root, "hip": hip, "knee": knee, "elbow": elbow}

def reference_mix(seconds: float = 3.5, fps: float = 30.0) -> torch.Tensor:
    """Joint positions (T, 22, 3) of procedural_mix on the average body: what a quirky fixture
    must retarget back to (up to the lift onto the ground)."""
    root, G = procedural_mix(seconds, fps)
    local = torch.stack([G[:, PARENTS[k]].transpose(-1, -2) @ G[:, k] for k in range(1, NUM_JOINTS)], 1)
    return forward_kinematics(root, G[:, 0], local, rest_offsets(None, torch.float64))[0]
