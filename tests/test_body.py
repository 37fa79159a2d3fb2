import itertools
import math

import pytest
import torch

from avatar_motor.body import rotations as rot
from avatar_motor.body.skeleton import (JOINT_NAMES, MIRROR, PARENTS, SHAPE_DIM, forward_kinematics, pelvis_height,
                                        rest_offsets, rest_positions, standing_height)

ORDERS = ["".join(p) for p in itertools.permutations("XYZ")] + ["XYX", "XZX", "YXY", "YZY", "ZXZ", "ZYZ"]


@pytest.fixture
def R():
    g = torch.Generator().manual_seed(0)
    return rot.axis_angle_to_matrix(torch.randn(500, 3, generator=g, dtype=torch.float64) * 1.5)


def test_smpl_joint_order_and_tree():
    assert JOINT_NAMES[:3] == ["pelvis", "left_hip", "right_hip"] and JOINT_NAMES[-1] == "right_wrist"
    assert len(JOINT_NAMES) == 22 and all(p < j for j, p in enumerate(PARENTS))
    assert [JOINT_NAMES[i] for i in MIRROR][1:3] == ["right_hip", "left_hip"]


def test_sixd_roundtrip(R):
    assert torch.allclose(rot.sixd_to_matrix(rot.matrix_to_6d(R)), R, atol=1e-10)


def test_quat_roundtrip(R):
    q = rot.matrix_to_quat(R)
    assert torch.allclose(rot.quat_to_matrix(q), R, atol=1e-10)
    assert (q[..., 0] >= 0).all()


def test_axis_angle_near_zero_agrees_with_quaternions_and_has_finite_gradients():
    # across the switch to the Taylor factors (|aa| = 1e-4) and at exactly zero
    for scale in (0.0, 1e-7, 9.9e-5, 1.01e-4, 1e-2, 3.0):
        aa = (torch.tensor([[0.3, -0.8, 0.52]], dtype=torch.float64) * scale).requires_grad_()
        R = rot.axis_angle_to_matrix(aa)
        assert torch.allclose(R, rot.quat_to_matrix(rot.axis_angle_to_quat(aa)), atol=1e-12)
        R.sum().backward()
        assert torch.isfinite(aa.grad).all()
    for dtype in (torch.float32, torch.float64):  # orthonormal in either precision
        R = rot.axis_angle_to_matrix(torch.randn(1000, 3, dtype=dtype) * 2)
        err = (R @ R.transpose(-1, -2) - torch.eye(3, dtype=dtype)).abs().max()
        assert err < (1e-5 if dtype == torch.float32 else 1e-12)


def test_axis_angle_roundtrip(R):
    aa = rot.matrix_to_axis_angle(R)
    assert torch.allclose(rot.axis_angle_to_matrix(aa), R, atol=1e-9)
    q = rot.axis_angle_to_quat(aa)
    assert torch.allclose(rot.quat_to_axis_angle(q), aa, atol=1e-9)


@pytest.mark.parametrize("order", ORDERS)
def test_euler_roundtrip_every_order(R, order):
    e = rot.matrix_to_euler(R, order)
    assert torch.allclose(rot.euler_to_matrix(e, order), R, atol=1e-9)


def test_euler_convention_matches_bvh():
    # ZXY with angles (a, b, c) means R = Rz(a) Rx(b) Ry(c)
    a = torch.tensor([[0.3, -0.2, 0.7]], dtype=torch.float64)
    Rz = rot.euler_to_matrix(torch.tensor([[0.3, 0, 0]], dtype=torch.float64), "ZXY")
    Rx = rot.euler_to_matrix(torch.tensor([[0, -0.2, 0]], dtype=torch.float64), "ZXY")
    Ry = rot.euler_to_matrix(torch.tensor([[0, 0, 0.7]], dtype=torch.float64), "ZXY")
    assert torch.allclose(rot.euler_to_matrix(a, "ZXY"), Rz @ Rx @ Ry)
    # Rz(0.3) turns +X towards +Y
    v = Rz[0] @ torch.tensor([1.0, 0, 0], dtype=torch.float64)
    assert torch.allclose(v, torch.tensor([0.3, 0.3, 0], dtype=torch.float64).cos() * torch.tensor([1.0, 0, 0], dtype=torch.float64)
                          + torch.tensor([0, 0.3, 0], dtype=torch.float64).sin())


def test_gimbal_lock_still_roundtrips():
    e = torch.tensor([[0.4, torch.pi / 2, -0.3]], dtype=torch.float64)
    R = rot.euler_to_matrix(e, "XYZ")
    assert torch.allclose(rot.euler_to_matrix(rot.matrix_to_euler(R, "XYZ"), "XYZ"), R, atol=1e-9)


def test_float32_works(R):
    R32 = R.float()
    assert rot.matrix_to_quat(R32).dtype == torch.float32
    assert torch.allclose(rot.quat_to_matrix(rot.matrix_to_quat(R32)), R32, atol=1e-5)


def test_slerp_endpoints_and_midpoint():
    a = rot.axis_angle_to_quat(torch.tensor([0.0, 0.0, 0.0], dtype=torch.float64))
    b = rot.axis_angle_to_quat(torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
    assert torch.allclose(rot.quat_slerp(a, b, 0.0), a) and torch.allclose(rot.quat_slerp(a, b, 1.0), b)
    mid = rot.quat_to_axis_angle(rot.quat_slerp(a, b, 0.5))
    assert torch.allclose(mid, torch.tensor([0.0, 0.5, 0.0], dtype=torch.float64), atol=1e-9)


def test_rotation_between_and_kabsch():
    g = torch.Generator().manual_seed(1)
    u, v = torch.randn(2, 3, generator=g, dtype=torch.float64)
    Rb = rot.rotation_between(u, v)
    assert torch.allclose(Rb @ rot.normalize(u), rot.normalize(v), atol=1e-9)
    assert torch.allclose(rot.rotation_between(u, -u) @ rot.normalize(u), -rot.normalize(u), atol=1e-9)
    Rt = rot.axis_angle_to_matrix(torch.tensor([0.3, -1.0, 0.5], dtype=torch.float64))
    src = torch.randn(4, 3, generator=g, dtype=torch.float64)
    assert torch.allclose(rot.kabsch(src, src @ Rt.T), Rt, atol=1e-9)


def test_turn_onto_is_rotation_between_away_from_opposite_directions():
    g = torch.Generator().manual_seed(2)
    u = torch.randn(500, 3, generator=g, dtype=torch.float64)
    v = u + 0.8 * torch.randn(500, 3, generator=g, dtype=torch.float64)
    keep = (rot.normalize(u) * rot.normalize(v)).sum(-1) > -0.9
    R = rot.turn_onto(u[keep], v[keep])
    assert torch.allclose(R, rot.rotation_between(u[keep], v[keep]), atol=1e-9)
    assert torch.allclose(R @ R.transpose(-1, -2), torch.eye(3, dtype=torch.float64).expand_as(R), atol=1e-9)


def test_shape_zero_is_average_and_components_do_what_they_say():
    z = torch.zeros(SHAPE_DIM)
    assert torch.allclose(rest_offsets(z, torch.float64), rest_offsets(None, torch.float64))
    assert 1.6 < standing_height(None) < 1.8
    tall = torch.zeros(SHAPE_DIM, dtype=torch.float64)
    tall[0] = 1.0
    assert abs(float(standing_height(tall)) - standing_height(None) - 0.10) < 1e-6
    long_legs = torch.zeros(SHAPE_DIM)
    long_legs[1] = 1.0
    assert pelvis_height(rest_offsets(long_legs)) > pelvis_height(rest_offsets(None))
    P = rest_positions(rest_offsets(None, torch.float64))
    assert abs(float(P[:, 1].min()) - 0.02) < 1e-9  # toes at the foot clearance
    assert (P[[1, 13, 16], 0] > 0).all()  # left side is +X


def test_fk_batched_any_shape_and_dtype():
    g = torch.Generator().manual_seed(0)
    for dtype in (torch.float32, torch.float64):
        lead = (2, 3, 4)
        rr = rot.axis_angle_to_matrix(torch.randn(*lead, 3, generator=g).to(dtype))
        lr = rot.axis_angle_to_matrix(torch.randn(*lead, 21, 3, generator=g).to(dtype) * 0.5)
        root = torch.randn(*lead, 3, generator=g).to(dtype)
        off = rest_offsets(torch.randn(*lead, SHAPE_DIM, generator=g), dtype)
        J, G = forward_kinematics(root, rr, lr, off)
        assert J.shape == (*lead, 22, 3) and G.shape == (*lead, 22, 3, 3) and J.dtype == dtype
        # bone lengths equal the offsets' lengths whatever the pose
        bones = (J[..., 1:, :] - J[..., PARENTS[1:], :]).norm(dim=-1)
        assert torch.allclose(bones, off[..., 1:, :].norm(dim=-1), atol=1e-5)
    # identity pose reproduces the rest positions
    off = rest_offsets(None, torch.float64)
    P = rest_positions(off)
    J, _ = forward_kinematics(P[0], torch.eye(3, dtype=torch.float64), torch.eye(3, dtype=torch.float64).repeat(21, 1, 1), off)
    assert torch.allclose(J, P)


def test_fk_equals_the_joint_by_joint_recursion():
    """forward_kinematics (pointer jumping for the rotations, one ancestry product for the
    positions) against the textbook recursion G_j = G_p L_j, P_j = P_p + G_p o_j."""
    g = torch.Generator().manual_seed(1)
    lead = (3, 5)
    rr = rot.axis_angle_to_matrix(torch.randn(*lead, 3, generator=g, dtype=torch.float64))
    lr = rot.axis_angle_to_matrix(torch.randn(*lead, 21, 3, generator=g, dtype=torch.float64))
    root = torch.randn(*lead, 3, generator=g, dtype=torch.float64)
    off = rest_offsets(torch.randn(*lead, SHAPE_DIM, generator=g), torch.float64)
    G, P = [rr], [root]
    for j in range(1, 22):
        p = PARENTS[j]
        G.append(G[p] @ lr[..., j - 1, :, :])
        P.append(P[p] + (G[p] @ off[..., j, :, None])[..., 0])
    J, Gs = forward_kinematics(root, rr, lr, off)
    assert torch.allclose(Gs, torch.stack(G, -3), atol=1e-12) and torch.allclose(J, torch.stack(P, -2), atol=1e-12)
    # the offsets may also be one skeleton for every frame
    J1, _ = forward_kinematics(root, rr, lr, off[0, 0])
    assert torch.allclose(J1[0, 0], J[0, 0], atol=1e-12)


def test_matrix_to_quat_takes_each_of_shepperds_branches():
    # the identity (trace largest) and half turns about X, Y, Z (each diagonal term largest in turn)
    for aa, q in (([0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]), ([math.pi, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]),
                  ([0.0, math.pi, 0.0], [0.0, 0.0, 1.0, 0.0]), ([0.0, 0.0, math.pi], [0.0, 0.0, 0.0, 1.0]),
                  ([0.0, 0.0, -3.1], None), ([2.0, -1.0, 0.5], None)):
        R = rot.axis_angle_to_matrix(torch.tensor(aa, dtype=torch.float64))
        got = rot.matrix_to_quat(R)
        assert torch.allclose(rot.quat_to_matrix(got), R, atol=1e-12)
        if q is not None:
            assert torch.allclose(got.abs(), torch.tensor(q, dtype=torch.float64), atol=1e-12)


def test_shape_validation():
    with pytest.raises(ValueError, match="body shape must have"):
        rest_offsets(torch.zeros(3))
