"""The skinned human (body/human.py, built by data/makehuman.py): the committed asset is a body
bound to our joints in our T-pose, fitted to any body shape, skinned exactly as glTF viewers skin
it, and written into glTF exports that the Khronos validator accepts."""
import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

from avatar_motor.body.human import human_mesh, skin
from avatar_motor.body.motion_state import pack
from avatar_motor.body.skeleton import (JOINT_INDEX, SHAPE_DIM, forward_kinematics, rest_offsets, rest_positions,
                                        standing_height)
from avatar_motor.io.gltf import read_glb, write_glb

ROOT = Path(__file__).resolve().parents[1]
VALIDATOR = ROOT / "web" / "tools" / "validate-gltf.mjs"


def test_the_asset_is_a_body_in_our_t_pose_bound_to_our_joints():
    V, F, J, W = human_mesh()
    assert V.shape == (13380, 3) and F.shape == (26756, 3) and int(F.max()) < len(V)
    assert J.shape == W.shape == (len(V), 4) and int(J.max()) < 22
    assert np.allclose(W.sum(1), 1.0, atol=1e-5) and (W >= 0).all()
    assert abs(float(V[:, 1].min())) < 0.02  # standing on the ground
    assert abs(float(V[:, 1].max()) - standing_height(None)) < 0.08  # as tall as our average body
    rest = rest_positions(rest_offsets(None, torch.float64)).numpy()
    for side, sign in (("left", 1), ("right", -1)):  # T-pose: the hands out to the sides, at the wrists
        hand = V[(J[:, 0] == JOINT_INDEX[f"{side}_wrist"]) & (W[:, 0] > 0.9)]
        assert len(hand) > 50 and (np.sign(hand[:, 0]) == sign).all()
        assert np.linalg.norm(hand.mean(0) - rest[JOINT_INDEX[f"{side}_wrist"]]) < 0.1


def test_the_low_detail_body_is_the_same_body_in_fewer_triangles():
    V, F, J, W = human_mesh()
    tall = torch.tensor([1.5, 0.5, 0.0, -0.5, 0.0, 0.0])
    for shape in (None, tall):
        Vf, _, Jf, Wf = human_mesh(shape)
        Vl, Fl, Jl, Wl = human_mesh(shape, "low")
        assert 1500 <= len(Fl) <= 3000 and int(Fl.max()) == len(Vl) - 1 and len(np.unique(Fl)) == len(Vl)
        assert not ((Fl[:, 0] == Fl[:, 1]) | (Fl[:, 1] == Fl[:, 2]) | (Fl[:, 0] == Fl[:, 2])).any()
        assert len(np.unique(np.sort(Fl, 1), axis=0)) == len(Fl)  # no two triangles on the same vertices
        # its vertices are vertices of the full body (fitted to the shape alike), with their weights
        d = np.linalg.norm(Vf[:, None] - Vl[None], axis=-1)  # (13,380 x V') pairwise
        nearest = d.argmin(0)
        assert d.min(0).max() < 1e-6
        assert (Jf[nearest] == Jl).all() and np.array_equal(Wf[nearest], Wl)
        # and the coarse surface stays near the full one: every full vertex within a few cm of it
        # (of points spread over its triangles)
        b = torch.tensor([(i / 6, j / 6) for i in range(7) for j in range(7 - i)], dtype=torch.float64)
        T = torch.from_numpy(Vl[Fl.astype(np.int64)]).double()  # (F', 3, 3)
        S = (T[:, None, 0] + b[None, :, :1] * (T[:, None, 1] - T[:, None, 0]) + b[None, :, 1:] * (T[:, None, 2] - T[:, None, 0]))
        S = S.reshape(-1, 3)
        near = torch.cat([torch.cdist(torch.from_numpy(c).double(), S).min(1).values for c in np.array_split(Vf, 20)]).numpy()
        assert np.percentile(near, 99) < 0.02 and near.max() < 0.05, (np.percentile(near, 99), near.max())
        # the same extent: standing on the ground, as tall, hands as far out
        assert np.abs(Vl.min(0) - Vf.min(0)).max() < 0.02 and np.abs(Vl.max(0) - Vf.max(0)).max() < 0.02
    with pytest.raises(ValueError, match="detail"):
        human_mesh(None, "medium")


def test_low_detail_keeps_original_vertices_on_a_grid_mesh():
    # a 30 x 30 grid of a bumpy sheet: the kept vertices are some of its own, the triangles index them
    from avatar_motor.data.makehuman import low_detail
    n = 30
    x, z = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
    V = np.stack((x.ravel(), 0.05 * np.sin(6 * x.ravel()) * np.cos(5 * z.ravel()), z.ravel()), 1).astype(np.float32)
    k = np.arange(n * n).reshape(n, n)
    quads = np.stack((k[:-1, :-1].ravel(), k[:-1, 1:].ravel(), k[1:, 1:].ravel(), k[1:, :-1].ravel()), 1)
    F = np.concatenate((quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]))
    keep, tris = low_detail(V, F, target=300)
    assert len(tris) <= 330 and len(np.unique(keep)) == len(keep) and int(tris.max()) == len(keep) - 1
    assert keep.min() >= 0 and keep.max() < len(V)
    area = np.linalg.norm(np.cross(V[keep][tris[:, 1]] - V[keep][tris[:, 0]], V[keep][tris[:, 2]] - V[keep][tris[:, 0]]), axis=1).sum() / 2
    assert abs(area - 1.0) < 0.05  # still the whole sheet


def test_the_body_follows_the_shape_parameters():
    V0 = human_mesh()[0]
    tall = torch.zeros(SHAPE_DIM)
    tall[0] = 2.0  # two steps of stature: 20 cm
    Vt = human_mesh(tall)[0]
    assert abs((Vt[:, 1].max() - V0[:, 1].max()) - 0.20) < 0.03
    assert abs(float(Vt[:, 1].min())) < 0.02  # still on the ground
    legs = torch.zeros(SHAPE_DIM)
    legs[1] = 2.0
    knee = JOINT_INDEX["left_knee"]
    J = human_mesh()[2]
    rest_legs = rest_positions(rest_offsets(legs, torch.float64)).numpy()
    at_knee = human_mesh(legs)[0][(J[:, 0] == knee)]
    assert abs(at_knee[:, 1].mean() - rest_legs[knee, 1]) < abs(V0[J[:, 0] == knee][:, 1].mean() - rest_legs[knee, 1])
    assert np.array_equal(human_mesh(torch.zeros(SHAPE_DIM))[0], V0)


def test_skinning_carries_each_vertex_rigidly_with_its_joint():
    torch.manual_seed(0)
    shape = torch.randn(SHAPE_DIM) * 0.5
    off = rest_offsets(shape, torch.float64)
    V, F, J, W = human_mesh(shape)
    rest = rest_positions(off).numpy()
    R = _rotations(22, 0.5)
    P, G = forward_kinematics(torch.tensor([0.3, 1.0, -0.2], dtype=torch.float64), R[0], R[1:], off)
    posed = skin(V.astype(np.float64), J, W, rest, G.numpy(), P.numpy())
    rigid = W[:, 0] > 1 - 1e-6  # bound to one joint alone
    j = J[rigid, 0].astype(np.int64)
    before = np.linalg.norm(V[rigid] - rest[j], axis=1)
    after = np.linalg.norm(posed[rigid] - P.numpy()[j], axis=1)
    assert rigid.sum() > 1000 and np.abs(before - after).max() < 1e-5


def _rotations(n: int, scale: float) -> torch.Tensor:
    """n random rotations (float64), of angles around `scale` rad."""
    A = torch.randn(n, 3, 3, dtype=torch.float64) * scale
    return torch.linalg.matrix_exp(A - A.mT)


def _motion(frames: int = 20) -> torch.Tensor:
    """World states (frames, 267) of a body that tumbles its joints while drifting forward."""
    torch.manual_seed(1)
    R = _rotations(frames * 22, 0.2).reshape(frames, 22, 3, 3)
    root = torch.tensor([0.0, 0.9, 0.0], dtype=torch.float64) + torch.linspace(0, 1, frames, dtype=torch.float64)[:, None] * \
        torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    P, _ = forward_kinematics(root, R[:, 0], R[:, 1:], rest_offsets(None, torch.float64))
    return pack(root, R[:, 0], R[:, 1:], P, torch.zeros_like(P)).float()


def test_gltf_export_skins_the_human_on_the_joint_nodes(tmp_path):
    X = _motion()
    shape = torch.tensor([1.0, -0.5, 0.5, 0.0, 0.5, -0.5])
    path = tmp_path / "walk.glb"
    write_glb(path, X, shape)
    doc, blob = read_glb(path)
    skin_ = doc["skins"][0]
    assert skin_["joints"] == list(range(22))
    prim = doc["meshes"][0]["primitives"][0]
    assert {"POSITION", "NORMAL", "JOINTS_0", "WEIGHTS_0"} <= set(prim["attributes"])
    acc = doc["accessors"][skin_["inverseBindMatrices"]]
    view = doc["bufferViews"][acc["bufferView"]]
    ibm = np.frombuffer(blob, np.float32, 22 * 16, view["byteOffset"]).reshape(22, 4, 4)
    rest = rest_positions(rest_offsets(shape, torch.float64)).numpy()
    assert np.allclose(ibm[:, 3, :3], -rest, atol=1e-6)  # bind pose = this body's rest pose
    roots = doc["scenes"][0]["nodes"]
    assert any(doc["nodes"][k].get("skin") == 0 for k in roots)  # the skinned mesh at the scene's root
    capsules = tmp_path / "capsules.glb"
    write_glb(capsules, X, shape, body="capsules")
    assert "skins" not in read_glb(capsules)[0]


@pytest.mark.skipif(not (shutil.which("node") and (ROOT / "web" / "node_modules" / "gltf-validator").exists()),
                    reason="node and the web packages (make web) are needed for the Khronos validator")
@pytest.mark.parametrize("detail", ["full", "low"])
def test_the_khronos_validator_accepts_the_skinned_export(tmp_path, detail):
    path = tmp_path / "walk.glb"
    write_glb(path, _motion(), torch.tensor([0.5, 0.0, -0.5, 0.5, 0.0, 0.0]), detail=detail)
    run = subprocess.run(["node", str(VALIDATOR), str(path)], capture_output=True, text=True, timeout=120)
    report = json.loads(run.stdout)
    assert report["errors"] == 0 and report["warnings"] == 0, report["messages"][:10]
