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
def test_the_khronos_validator_accepts_the_skinned_export(tmp_path):
    path = tmp_path / "walk.glb"
    write_glb(path, _motion(), torch.tensor([0.5, 0.0, -0.5, 0.5, 0.0, 0.0]))
    run = subprocess.run(["node", str(VALIDATOR), str(path)], capture_output=True, text=True, timeout=120)
    report = json.loads(run.stdout)
    assert report["errors"] == 0 and report["warnings"] == 0, report["messages"][:10]
