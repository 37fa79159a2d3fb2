"""glTF 2.0 binary (.glb) export: the canonical skeleton as a node hierarchy and one animation clip
(root translation + every joint's local rotation), with a body: the skinned human (body/human.py:
one mesh, a skin over the joint nodes, the avatar's rest pose as the bind pose) or the capsule
mannequin of our own (a cylinder per bone, a sphere per joint, parented to the joints). Opens in any
glTF viewer; Y up, metres, like our world.
"""
from __future__ import annotations

import json
import math
import struct
from pathlib import Path

import numpy as np
import torch

from ..body import rotations as rot
from ..body.skeleton import JOINT_NAMES, PARENTS, rest_offsets
from ..body.motion_state import unpack

_FLOAT, _UINT16, _UINT8 = 5126, 5123, 5121
# each body's one material: skin tones for the human, the studio's blue for the mannequin
_MATERIALS = {
    "human": {"name": "skin", "pbrMetallicRoughness": {"baseColorFactor": [0.80, 0.62, 0.52, 1.0], "metallicFactor": 0.0,
                                                       "roughnessFactor": 0.7}},
    "capsules": {"name": "skin", "pbrMetallicRoughness": {"baseColorFactor": [0.45, 0.62, 0.85, 1.0], "metallicFactor": 0.0,
                                                          "roughnessFactor": 0.6}},
}
BODIES = tuple(_MATERIALS)
_ARRAY, _ELEMENTS = 34962, 34963


def _cylinder(n: int = 12) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit-radius cylinder of height 1 along +Y from y=0 to y=1."""
    a = np.linspace(0, 2 * math.pi, n, endpoint=False)
    ring = np.stack((np.cos(a), np.zeros(n), np.sin(a)), 1)
    pos = np.concatenate((ring, ring + [0, 1, 0])).astype(np.float32)
    nrm = np.concatenate((ring, ring)).astype(np.float32)
    idx = []
    for i in range(n):
        j = (i + 1) % n
        idx += [i, i + n, j, j, i + n, j + n]
    return pos, nrm, np.array(idx, np.uint16)


def _sphere(n: int = 10) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    pos = []
    for i in range(n + 1):
        th = math.pi * i / n
        for k in range(2 * n):
            ph = 2 * math.pi * k / (2 * n)
            pos.append((math.sin(th) * math.cos(ph), math.cos(th), math.sin(th) * math.sin(ph)))
    pos = np.array(pos, np.float32)
    idx = []
    m = 2 * n
    for i in range(n):
        for k in range(m):
            a, b = i * m + k, i * m + (k + 1) % m
            c, d = a + m, b + m
            idx += [a, c, b, b, c, d]
    return pos, pos.copy(), np.array(idx, np.uint16)


class _Builder:
    def __init__(self):
        self.bin = bytearray()
        self.views, self.accessors = [], []

    def add(self, arr: np.ndarray, comp: int, typ: str, target: int | None = None, minmax: bool = False) -> int:
        while len(self.bin) % 4:
            self.bin.append(0)
        data = np.ascontiguousarray(arr).tobytes()
        view = {"buffer": 0, "byteOffset": len(self.bin), "byteLength": len(data)}
        if target:
            view["target"] = target
        self.bin += data
        self.views.append(view)
        acc = {"bufferView": len(self.views) - 1, "componentType": comp, "count": int(arr.shape[0]), "type": typ}
        if minmax:
            acc["min"] = arr.min(0).astype(float).tolist() if arr.ndim > 1 else [float(arr.min())]
            acc["max"] = arr.max(0).astype(float).tolist() if arr.ndim > 1 else [float(arr.max())]
        self.accessors.append(acc)
        return len(self.accessors) - 1


def _capsules(B: _Builder, nodes: list, names: list[str], off: np.ndarray) -> list:
    """The capsule mannequin: a sphere per joint and a cylinder per bone, children of the joint
    nodes (rigid parts). Returns the meshes."""
    meshes = []
    for name, (p, n, i) in (("bone", _cylinder()), ("joint", _sphere())):
        prim = {"attributes": {"POSITION": B.add(p, _FLOAT, "VEC3", _ARRAY, True), "NORMAL": B.add(n, _FLOAT, "VEC3", _ARRAY)},
                "indices": B.add(i, _UINT16, "SCALAR", _ELEMENTS), "material": 0}
        meshes.append({"name": name, "primitives": [prim]})
    radius = [0.09, 0.075, 0.075, 0.08, 0.06, 0.06, 0.08, 0.045, 0.045, 0.09, 0.035, 0.035, 0.05, 0.05, 0.05, 0.1,
              0.05, 0.05, 0.04, 0.04, 0.035, 0.035]
    for j in range(len(names)):
        r = radius[j] * 1.1
        nodes.append({"name": f"{names[j]}_ball", "mesh": 1, "scale": [r, r, r]})
        nodes[j]["children"].append(len(nodes) - 1)
        if j == 0:
            continue
        p = PARENTS[j]
        d = off[j]
        length = float(np.linalg.norm(d))
        if length < 1e-6:
            continue
        qa = rot.matrix_to_quat(rot.rotation_between(torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64),
                                                     torch.from_numpy(d))).numpy()
        rr = min(radius[j], radius[p]) * 0.9
        nodes.append({"name": f"{names[p]}_to_{names[j]}", "mesh": 0, "scale": [rr, length, rr],
                      "rotation": [float(qa[1]), float(qa[2]), float(qa[3]), float(qa[0])]})
        nodes[p]["children"].append(len(nodes) - 1)
    return meshes


def _human(B: _Builder, nodes: list, shape, off: np.ndarray, detail: str = "full") -> tuple[list, list, list]:
    """The skinned human fitted to the body (body/human.py) as one mesh node at the scene's root,
    skinned by the joint nodes; its bind pose is the rest pose (T-pose on these bones, standing on
    the ground), so each inverse bind matrix is the translation by minus the joint's rest position.
    Returns the meshes, the skins and the scene's root nodes."""
    from ..body.human import LICENCE, human_mesh, vertex_normals
    from ..body.skeleton import rest_positions
    V, F, Jn, W = human_mesh(shape, detail)
    rest = rest_positions(torch.from_numpy(off)).numpy()
    ibm = np.tile(np.eye(4, dtype=np.float32), (len(rest), 1, 1))
    ibm[:, 3, :3] = -rest  # glTF is column-major: the translation is elements 12-14, this row-major row 3
    prim = {"attributes": {"POSITION": B.add(V, _FLOAT, "VEC3", _ARRAY, True),
                           "NORMAL": B.add(vertex_normals(V, F), _FLOAT, "VEC3", _ARRAY),
                           "JOINTS_0": B.add(Jn, _UINT8, "VEC4", _ARRAY), "WEIGHTS_0": B.add(W, _FLOAT, "VEC4", _ARRAY)},
            "indices": B.add(F.reshape(-1), _UINT16, "SCALAR", _ELEMENTS), "material": 0}
    nodes.append({"name": "human", "mesh": 0, "skin": 0, "extras": {"licence": LICENCE}})
    skins = [{"name": "skeleton", "joints": list(range(len(rest))), "skeleton": 0,
              "inverseBindMatrices": B.add(ibm.reshape(len(rest), 16), _FLOAT, "MAT4")}]
    return [{"name": "human", "primitives": [prim]}], skins, [0, len(nodes) - 1]


def write_glb(path, states: torch.Tensor, shape: torch.Tensor | None = None, fps: float = 30.0,
              names: list[str] | None = None, body: str = "human", detail: str = "full") -> None:
    """names: the joints' node names (default ours; io/skeletons.py); body: "human" (skinned) or
    "capsules"; detail: the human's mesh, "full" or "low" (body/human.py)."""
    if body not in BODIES:
        raise ValueError(f"unknown body {body!r}; bodies are {list(BODIES)}")
    names = list(names or JOINT_NAMES)
    u = unpack(states.double())
    T = states.shape[0]
    off = rest_offsets(shape, torch.float64).numpy()
    local = u.rotations
    q = rot.matrix_to_quat(local).numpy()  # (T, 22, w x y z)
    q_xyzw = np.concatenate((q[..., 1:], q[..., :1]), -1).astype(np.float32)
    B = _Builder()
    materials = [_MATERIALS[body]]
    nodes = []
    for j, name in enumerate(names):
        node = {"name": name, "translation": (u.root_pos[0].tolist() if j == 0 else off[j].tolist()),
                "rotation": q_xyzw[0, j].tolist(), "children": []}
        nodes.append(node)
    for j in range(1, len(JOINT_NAMES)):
        nodes[PARENTS[j]]["children"].append(j)
    extra: dict = {}
    if body == "human":
        meshes, skins, roots = _human(B, nodes, shape, off, detail)
        extra["skins"] = skins
    else:
        meshes, roots = _capsules(B, nodes, names, off), [0]
    for nd in nodes:
        if "children" in nd and not nd["children"]:
            del nd["children"]
    times = (np.arange(T) / fps).astype(np.float32)
    t_acc = B.add(times, _FLOAT, "SCALAR", minmax=True)
    samplers, channels = [], []
    samplers.append({"input": t_acc, "output": B.add(u.root_pos.numpy().astype(np.float32), _FLOAT, "VEC3"), "interpolation": "LINEAR"})
    channels.append({"sampler": 0, "target": {"node": 0, "path": "translation"}})
    for j in range(len(JOINT_NAMES)):
        samplers.append({"input": t_acc, "output": B.add(q_xyzw[:, j], _FLOAT, "VEC4"), "interpolation": "LINEAR"})
        channels.append({"sampler": len(samplers) - 1, "target": {"node": j, "path": "rotation"}})
    doc = {
        "asset": {"version": "2.0", "generator": "avatar-motor"},
        "scene": 0, "scenes": [{"nodes": roots}], "nodes": nodes, "meshes": meshes, "materials": materials, **extra,
        "animations": [{"name": "motion", "samplers": samplers, "channels": channels}],
        "buffers": [{"byteLength": len(B.bin)}], "bufferViews": B.views, "accessors": B.accessors,
    }
    js = json.dumps(doc, separators=(",", ":")).encode()
    js += b" " * (-len(js) % 4)
    bn = bytes(B.bin) + b"\0" * (-len(B.bin) % 4)
    total = 12 + 8 + len(js) + 8 + len(bn)
    data = (struct.pack("<4sII", b"glTF", 2, total) + struct.pack("<I4s", len(js), b"JSON") + js
            + struct.pack("<I4s", len(bn), b"BIN\0") + bn)
    if hasattr(path, "write"):  # a file object (the server answers from memory)
        path.write(data)
    else:
        Path(path).write_bytes(data)


def read_glb(path: str | Path) -> tuple[dict, bytes]:
    data = Path(path).read_bytes()
    magic, version, total = struct.unpack_from("<4sII", data, 0)
    if magic != b"glTF" or version != 2 or total != len(data):
        raise ValueError(f"{path}: not a glTF 2.0 binary file")
    jl, jt = struct.unpack_from("<I4s", data, 12)
    doc = json.loads(data[20:20 + jl])
    bl, bt = struct.unpack_from("<I4s", data, 20 + jl)
    return doc, data[28 + jl:28 + jl + bl]


def read_glb_joints(path: str | Path) -> tuple[list[str], np.ndarray]:
    """The joints a .glb animates and their world positions (T, J, 3) at every key of its first
    animation: the node hierarchy evaluated from the file alone (translations and rotations; the
    scale of our joint nodes is one), as a viewer would show it. For checking exports."""
    doc, blob = read_glb(path)
    width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}

    def accessor(i: int) -> np.ndarray:
        a = doc["accessors"][i]
        view = doc["bufferViews"][a["bufferView"]]
        n = width[a["type"]]
        start = view.get("byteOffset", 0) + a.get("byteOffset", 0)
        return np.frombuffer(blob, np.float32, a["count"] * n, start).reshape(a["count"], n).astype(np.float64)

    anim = doc["animations"][0]
    T = doc["accessors"][anim["samplers"][0]["input"]]["count"]
    nodes = doc["nodes"]
    trans = [np.tile(nd.get("translation", [0.0, 0.0, 0.0]), (T, 1)).astype(np.float64) for nd in nodes]
    quat = [np.tile(nd.get("rotation", [0.0, 0.0, 0.0, 1.0]), (T, 1)).astype(np.float64) for nd in nodes]
    animated = []
    for ch in anim["channels"]:
        k, what = ch["target"]["node"], ch["target"]["path"]
        out = accessor(anim["samplers"][ch["sampler"]]["output"])
        if what == "translation":
            trans[k] = out
        elif what == "rotation":
            quat[k] = out
        if k not in animated:
            animated.append(k)
    parent = {c: p for p, nd in enumerate(nodes) for c in nd.get("children", [])}
    world: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def place(k: int) -> tuple[np.ndarray, np.ndarray]:
        if k not in world:
            q = torch.from_numpy(quat[k][:, [3, 0, 1, 2]])  # x, y, z, w -> w, x, y, z
            R = rot.quat_to_matrix(q / q.norm(dim=-1, keepdim=True)).numpy()
            if k in parent:
                Rp, tp = place(parent[k])
                world[k] = (Rp @ R, tp + np.einsum("tij,tj->ti", Rp, trans[k]))
            else:
                world[k] = (R, trans[k])
        return world[k]

    animated.sort()
    return [nodes[k]["name"] for k in animated], np.stack([place(k)[1] for k in animated], 1)
