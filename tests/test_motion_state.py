import pytest
import torch

from avatar_motor.body import rotations as rot
from avatar_motor.body.skeleton import SHAPE_DIM, forward_kinematics, rest_offsets
from avatar_motor.data.cache import MotionCache
from avatar_motor.data.dataset import Normalizer, SegmentConfig, SegmentDataset
from avatar_motor.body.motion_state import (STATE_DIM, canonicalize, facing_yaw, joints_of, pack, states_from_motion,
                                            to_world, unpack, velocities_of)

from .fixture_tools import FIXTURES


def random_states(B=4, T=16, seed=0):
    g = torch.Generator().manual_seed(seed)
    root = torch.randn(B, T, 3, generator=g, dtype=torch.float64)
    rr = rot.axis_angle_to_matrix(torch.randn(B, T, 3, generator=g, dtype=torch.float64))
    lr = rot.axis_angle_to_matrix(torch.randn(B, T, 21, 3, generator=g, dtype=torch.float64) * 0.4)
    return states_from_motion(root, rr, lr, rest_offsets(torch.randn(B, SHAPE_DIM, generator=g), torch.float64))


def test_pack_unpack_roundtrip():
    x = random_states()
    assert x.shape == (4, 16, STATE_DIM)
    u = unpack(x)
    assert torch.allclose(pack(u.root_pos, u.root_rot, u.local_rot, u.joints, u.velocities), x, atol=1e-10)


def test_velocities_are_backward_differences_per_second():
    x = random_states()
    J, V = joints_of(x), velocities_of(x)
    assert torch.allclose(V[:, 1:], (J[:, 1:] - J[:, :-1]) * 30, atol=1e-9)


def test_canonicalize_to_world_exact_inverse_and_frame():
    x = random_states()
    xc, tf = canonicalize(x)
    assert (to_world(xc, tf) - x).abs().max() < 1e-9
    J0 = joints_of(xc[:, 0])
    assert torch.allclose(J0[:, 0, [0, 2]], torch.zeros(4, 2, dtype=torch.float64), atol=1e-9)  # pelvis over origin
    assert torch.allclose(J0[:, 0, 1], joints_of(x[:, 0])[:, 0, 1])  # height kept
    assert facing_yaw(J0).abs().max() < 1e-9  # faces +Z
    left = J0[:, 1] - J0[:, 2]
    assert (left[:, 0] > 0).all() and left[:, 2].abs().max() < 1e-9  # hips' axis along +X
    # canonical states are still consistent with FK
    u = unpack(xc)
    Jfk, _ = forward_kinematics(u.root_pos, u.root_rot, u.local_rot, rest_offsets(None, torch.float64))
    # (shapes differ per sample, so compare bone directions instead of positions)
    d1 = (Jfk[..., 4, :] - Jfk[..., 1, :])
    d2 = (u.joints[..., 4, :] - u.joints[..., 1, :])
    assert torch.allclose(rot.normalize(d1), rot.normalize(d2), atol=1e-9)


def _cache_from_fixtures(tmp_path):
    from avatar_motor.data.cache import import_motion
    path, _ = import_motion(FIXTURES, name="fixtures", progress=False, workers=1)
    return MotionCache.load(path)


def test_segment_dataset_windows(tmp_path):
    cache = _cache_from_fixtures(tmp_path)
    ds = SegmentDataset([cache], SegmentConfig(frames=15, split="all"))
    g = torch.Generator().manual_seed(0)
    x, shapes = ds.sample(32, g)
    assert x.shape == (32, 16, STATE_DIM) and shapes.shape == (32, SHAPE_DIM)
    J = joints_of(x)
    assert J[:, 0, 0, [0, 2]].abs().max() < 1e-5 and facing_yaw(J[:, 0]).abs().max() < 1e-5
    # joints are the FK of the rotations with each sample's own shape
    from avatar_motor.train.losses import fk_joints
    assert (fk_joints(x.double(), shapes) - J).abs().max() < 1e-4
    # velocity of the initial state is real (backward difference from the frame before it)
    assert velocities_of(x)[:, 0].abs().max() > 0


def test_mirroring_and_shape_scaling(tmp_path):
    cache = _cache_from_fixtures(tmp_path)
    ds = SegmentDataset([cache], SegmentConfig(split="all"))
    starts = ds.window_starts[:4]
    base, _ = ds.windows(starts, shapes=torch.zeros(4, SHAPE_DIM), mirror=torch.zeros(4, dtype=torch.bool))
    mir, _ = ds.windows(starts, shapes=torch.zeros(4, SHAPE_DIM), mirror=torch.ones(4, dtype=torch.bool))
    from avatar_motor.body.skeleton import MIRROR
    Jb, Jm = joints_of(base), joints_of(mir)
    assert torch.allclose(Jm[..., 0], -Jb[..., MIRROR, 0], atol=1e-5)
    assert torch.allclose(Jm[..., 1:], Jb[..., MIRROR, 1:], atol=1e-5)
    tall = torch.zeros(4, SHAPE_DIM)
    tall[:, 0] = 2.0
    big, _ = ds.windows(starts, shapes=tall, mirror=torch.zeros(4, dtype=torch.bool))
    ratio = joints_of(big)[:, 0, 0, 1] / Jb[:, 0, 0, 1]  # pelvis height scales with leg length
    assert (ratio > 1.05).all()
    # travelled distance scales by the same ratio
    d_big = joints_of(big)[:, -1, 0, [0, 2]].norm(dim=-1)
    d_base = Jb[:, -1, 0, [0, 2]].norm(dim=-1)
    assert torch.allclose(d_big, d_base * ratio, rtol=1e-3, atol=1e-4)


def test_normalizer_roundtrip_and_validation():
    x = random_states().float().reshape(-1, STATE_DIM)
    n = Normalizer(x.mean(0), x.std(0).clamp_min(1e-2))
    assert torch.allclose(n.decode(n.encode(x)), x, atol=1e-5)
    n2 = Normalizer.from_dict(n.to_dict())
    assert torch.equal(n2.mean, n.mean)
    with pytest.raises(ValueError):
        Normalizer.from_dict({"mean": [0.0] * 3, "std": [1.0] * 3})


def test_horizontal_zeroes_the_vertical_axis_and_keeps_the_dtype():
    from avatar_motor.body.motion_state import horizontal
    v = torch.tensor([[1.5, -2.0, 3.0]], dtype=torch.float64)
    h = horizontal(v)
    assert h.dtype == torch.float64 and h.tolist() == [[1.5, 0.0, 3.0]]
    assert horizontal(v.float()).dtype == torch.float32
