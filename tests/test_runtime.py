import math

import pytest
import torch

from avatar_motor.body import rotations as rot
from avatar_motor.body.skeleton import FOOT_CLEARANCE, SHAPE_DIM, forward_kinematics, rest_offsets
from avatar_motor.body.motion_state import FPS, SLICES, body_mismatch, joints_of, pack, unpack, velocities_of
from avatar_motor.runtime.crowd import IMPULSE_PRESETS, Avatar, Crowd, standing_state
from avatar_motor.runtime.guidance import facing_loss_and_grad, move_loss_and_grad
from avatar_motor.runtime.processing import inertialize, snap_to_ground, solve_body, two_bone_ik

from .conftest_models import shipped_or_tiny, tiny_motor
from .test_motion_state import random_states


@pytest.fixture
def motor(tmp_path):
    return tiny_motor(tmp_path)


def test_standing_state_is_on_the_ground_and_consistent():
    x = standing_state()
    J = joints_of(x)
    assert abs(float(J[:, 1].min()) - FOOT_CLEARANCE) < 1e-6
    assert float(body_mismatch(x.double(), rest_offsets(None, torch.float64)).max()) < 1e-6
    assert float(J[20, 1]) < 1.1  # arms lowered, not a T-pose


def test_snap_puts_lowest_joint_of_segment_on_ground():
    seg = random_states(B=3, T=15).float()
    out = snap_to_ground(seg)
    low = joints_of(out)[..., 1].amin((-1, -2))
    assert torch.allclose(low, torch.full((3,), FOOT_CLEARANCE), atol=1e-6)
    assert torch.allclose(out[..., 1] - seg[..., 1], joints_of(out)[..., 0, 1] - joints_of(seg)[..., 0, 1])  # rigid shift


def walk_states(T=16):
    from avatar_motor.body.skeleton import PARENTS
    from avatar_motor.body.motion_state import states_from_motion
    from .fixture_tools import procedural_walk
    root, G = procedural_walk(T + 8)
    local = torch.stack([G[:, PARENTS[k]].transpose(-1, -2) @ G[:, k] for k in range(1, 22)], 1)
    x = states_from_motion(root, G[:, 0], local, rest_offsets(None, torch.float64))
    return torch.stack((x[:T], x[8:8 + T]))


def test_inertialization_is_continuous_then_decays():
    x = walk_states()
    x0, seg = x[:, 0], x[:, 1:].clone()
    seg[..., 135:201] += 0.3  # a jump at the segment start
    out = inertialize(x0, seg, halflife=0.1)
    J = joints_of(out)
    clean = joints_of(inertialize(x0, x[:, 1:], halflife=0.1))
    # the jump is hidden at the join: frame 1 lands where it would have without the jump
    assert (J[:, 0] - clean[:, 0]).abs().max() < 0.3 * 0.1
    late = (J[:, -1] - joints_of(seg)[:, -1]).abs().max()
    assert late < 0.02 * 0.3  # offset almost gone after 0.5 s
    assert torch.allclose(velocities_of(out)[:, 1:], (J[:, 1:] - J[:, :-1]) * FPS, atol=1e-6)
    # an impulse in x0's velocity is not extrapolated into a broken skeleton
    kicked = x0.clone()
    kicked[:, 201 + 45:201 + 48] += 30.0  # head flung at 30 m/s
    bones = lambda s: (joints_of(s)[..., 15, :] - joints_of(s)[..., 12, :]).norm(dim=-1)  # noqa: E731
    assert torch.allclose(bones(inertialize(kicked, x[:, 1:], 0.1)), bones(x[:, 1:]), atol=0.02)
    # rotations blend too: frame 1 is close to the initial state's rotation
    u0, u = unpack(x0), unpack(out)
    assert (u.root_rot[:, 0] - u0.root_rot).abs().max() < 0.1


def test_the_body_stage_makes_one_body_and_keeps_the_feet_above_ground():
    x = walk_states()
    off = rest_offsets(torch.randn(2, SHAPE_DIM, generator=torch.Generator().manual_seed(1)), torch.float64)
    u = unpack(x)
    wrong = rot.axis_angle_to_matrix(torch.randn(2, x.shape[1], 21, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64) * 0.3)
    two = pack(u.root_pos, u.root_rot, wrong @ u.local_rot, u.joints - torch.tensor([0.0, 0.15, 0.0], dtype=torch.float64), u.velocities)
    for follow in (None, 0.0, 1.0):
        out = solve_body(x[:, 0], two[:, 1:], off, follow)
        assert float(body_mismatch(out, off[:, None]).max()) < 1e-9  # FK of its own rotations, on its own bones
        J = joints_of(out)
        assert torch.allclose(J[..., 0, :], joints_of(two[:, 1:])[..., 0, :])  # the pelvis is kept
        assert torch.allclose(velocities_of(out), (J - torch.cat((joints_of(x[:, :1]), J[:, :-1]), 1)) * FPS)
        if follow is not None:  # the processed body was 15 cm under the ground: legs bend to keep feet up
            assert float(J[..., [7, 8, 10, 11], 1].min()) > -1e-6
    # following: the ankles land on their processed locations where the legs reach them
    target = joints_of(x[:, 1:])
    out = joints_of(solve_body(x[:, 0], pack(u.root_pos, u.root_rot, wrong @ u.local_rot, u.joints, u.velocities)[:, 1:],
                               rest_offsets(None, torch.float64).expand(2, 22, 3), 1.0))
    assert (out[..., [7, 8], :] - target[..., [7, 8], :]).norm(dim=-1).max() < 1e-3  # a straight leg stops 0.1 mm short
    assert (out[..., [10, 11], :] - target[..., [10, 11], :]).norm(dim=-1).max() < 1e-3


def test_the_body_stage_lifts_a_sinking_trunk_onto_the_ground_pose_unchanged():
    """A body tipping over whose head and back dip under the ground is lifted per frame onto the
    ground: its lowest joint at 0, its trunk's and arms' rotations and the frames above the ground
    as they were."""
    off = rest_offsets(None, torch.float64).expand(2, 22, 3)
    still = standing_state().double()[None, None].repeat(2, 16, 1)
    u = unpack(still)
    pitch = torch.linspace(0.0, 3.0, 16, dtype=torch.float64)  # tipping over backward onto the back
    root_rot = rot.axis_angle_to_matrix(torch.stack((-pitch, 0 * pitch, 0 * pitch), -1))[None].expand(2, 16, 3, 3)
    root = u.root_pos.clone()
    root[..., 1] = 0.3  # the pelvis low: the head goes under as the body tips
    J, _ = forward_kinematics(root, root_rot, u.local_rot, off[:, None])
    seg = pack(root, root_rot, u.local_rot, J, torch.zeros_like(J))
    out = solve_body(still[:, 0], seg, off, 0.0)
    Jo, uo = joints_of(out), unpack(out)
    assert float(J[..., 1].min()) < -0.3  # it did sink
    assert float(Jo[..., 1].min()) > -1e-9 and torch.allclose(Jo[..., 1].amin(-1).clamp(max=0.0), torch.zeros(2, 16, dtype=torch.float64))
    trunk_and_arms = [j - 1 for j in range(1, 22) if j not in (1, 2, 4, 5, 7, 8)]  # the legs may bend to stay up
    assert torch.allclose(uo.local_rot[:, :, trunk_and_arms], u.local_rot[:, :, trunk_and_arms])
    assert torch.allclose(uo.root_rot, root_rot)
    above = J[..., 1].amin(-1) >= 0  # frames that were above the ground are untouched
    assert above.any() and torch.allclose(Jo[above], J[above])
    assert float(body_mismatch(out, off[:, None]).max()) < 1e-9


def test_a_pinned_foot_stays_where_it_stood_whatever_the_rotations_do():
    off = rest_offsets(None, torch.float64).expand(2, 22, 3)
    # a standing body whose rotations slowly spread its legs: both feet would slide apart
    still = standing_state().double()[None, None].repeat(2, 16, 1)
    u = unpack(still)
    spread = torch.linspace(0.0, 0.2, 16, dtype=torch.float64)[None, :, None].expand(2, 16, 1)
    local = u.local_rot.clone()
    for hip, sgn in ((1, 1.0), (2, -1.0)):  # hips abduct about Z
        local[:, :, hip - 1] = rot.axis_angle_to_matrix(torch.cat((0 * spread, 0 * spread, sgn * spread), -1)) @ local[:, :, hip - 1]
    moved = pack(u.root_pos, u.root_rot, local, u.joints, u.velocities)
    x0 = still[:, 0]
    free = joints_of(solve_body(x0, moved[:, 1:], off, 0.0))
    pinned = joints_of(solve_body(x0, moved[:, 1:], off, 0.0, pin=True))
    feet = [10, 11]
    planted = joints_of(x0)[:, feet]
    slide = lambda J: float(((J[:, :, feet] - planted[:, None]) * torch.tensor([1.0, 0, 1.0], dtype=torch.float64)).norm(dim=-1).max())  # noqa: E731
    low = bool((joints_of(x0)[:, feet, 1] < 0.06).all())
    assert low and slide(free) > 0.05 and slide(pinned) < 1e-3
    assert float(body_mismatch(solve_body(x0, moved[:, 1:], off, 0.0, pin=True), off[:, None]).max()) < 1e-9


def test_two_bone_ik_reaches_keeps_bones_and_bends_a_straight_knee_forward():
    a = torch.zeros(3, 3, dtype=torch.float64)
    b = torch.tensor([[0.0, -0.4, 0.0], [0.0, -0.4, 0.05], [0.0, -0.4, 0.05]], dtype=torch.float64)
    c = torch.tensor([[0.0, -0.8, 0.0], [0.0, -0.8, 0.0], [0.0, -0.8, 0.0]], dtype=torch.float64)
    t = torch.tensor([[0.0, -0.6, 0.0], [0.2, -0.5, 0.3], [0.0, -2.0, 0.0]], dtype=torch.float64)  # last: out of reach
    R_a, R_b = two_bone_ik(a, b, c, t, torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64).expand(3, 3))
    b2 = a + (R_a @ (b - a)[..., None])[..., 0]
    c2 = b2 + (R_a @ R_b @ (c - b)[..., None])[..., 0]
    assert torch.allclose((b2 - a).norm(dim=-1), (b - a).norm(dim=-1)) and torch.allclose((c2 - b2).norm(dim=-1), (c - b).norm(dim=-1))
    assert (c2[:2] - t[:2]).norm(dim=-1).max() < 1e-9
    assert float(b2[0, 2]) > 0.1  # the straight leg's knee bent forward (about +X: the shin goes back)
    assert float(rot.normalize(c2[2])[1]) < -0.999  # unreachable: stretched toward it


def test_every_stage_choice_ends_as_one_body(motor):
    from avatar_motor.runtime.crowd import RuntimeConfig
    from avatar_motor.runtime.stages import STAGES
    for stages in ((), ("snap",), ("fuse_velocities", "lock_feet", "fk"), tuple(STAGES)):
        crowd = Crowd(motor, RuntimeConfig(stages=stages), seed=1)
        ids = [crowd.spawn(shape=torch.randn(SHAPE_DIM, generator=torch.Generator().manual_seed(k)), position=(k, 0.0)) for k in range(2)]
        crowd.set_goal(ids[1], (1.0, 0.0))
        for _ in range(2):
            out = crowd.step_segment()
            for i in ids:
                off = rest_offsets(crowd.avatars[i].shape, torch.float64)
                assert float(body_mismatch(out[i].double(), off).max()) < 1e-5, stages
    with pytest.raises(ValueError, match="unknown post-processing stage.*'smoth'"):
        Crowd(motor, RuntimeConfig(stages=("smoth",)))


def test_determinism_per_seed(motor):
    a = Avatar(motor, seed=5).rollout(32)
    b = Avatar(motor, seed=5).rollout(32)
    c = Avatar(motor, seed=6).rollout(32)
    assert torch.equal(a, b) and not torch.equal(a, c)


def test_crowd_equals_individual_avatars(tmp_path):
    from avatar_motor.runtime.crowd import RuntimeConfig
    # in float32; in bfloat16 a row depends on its batch by millimetres (the shipped model, 4
    # segments: 4.8 mm against 0.004 mm; RuntimeConfig.bfloat16_from). A trained model: a random
    # one's rotations are noise, up to half a turn from x0's at each join, where inertialize's
    # linear blend of the 6D channels passes near degenerate frames and magnifies float noise to 2e-4
    motor = shipped_or_tiny(tmp_path)
    cfg = RuntimeConfig(bfloat16_from=0)
    shapes = torch.randn(3, SHAPE_DIM, generator=torch.Generator().manual_seed(0))
    crowd = Crowd(motor, cfg, seed=2)
    ids = [crowd.spawn(shape=shapes[k], position=(k, 0.0)) for k in range(3)]
    crowd.set_goal(ids[1], (1.0, 0.0))
    together = [crowd.step_segment() for _ in range(2)]
    for k in range(3):
        solo = Crowd(motor, cfg, seed=2)
        solo._next_id = k  # same id -> same noise stream
        i = solo.spawn(shape=shapes[k], position=(k, 0.0))
        if k == 1:
            solo.set_goal(i, (1.0, 0.0))
        alone = [solo.step_segment()[i] for _ in range(2)]
        for t in range(2):
            # the network's float32 batch arithmetic differs by ~1e-6; velocities are differences x 30 fps
            d = (together[t][ids[k]] - alone[t]).abs()
            assert d[:, :SLICES["velocities"].start].max() < 1e-4 and d[:, SLICES["velocities"]].max() < 3e-3


def test_command_takes_effect_at_the_next_frame(tmp_path):
    crowd = Crowd(shipped_or_tiny(tmp_path), seed=0)  # a trained model: a random one's frames jump anywhere
    i = crowd.spawn()
    crowd.next_frames()
    assert len(crowd.avatars[i].queue) == 14
    shown = crowd.avatars[i].state
    crowd.push(i, "head", (0.0, 0.0, 3.0))
    assert crowd.avatars[i].queue == []
    nxt = crowd.next_frames()[i]
    # the new segment starts from the shown frame, with the push in its initial velocity
    assert float((joints_of(nxt)[0] - joints_of(shown)[0]).norm()) < 0.2


def _shaped_crowd(motor, seed):
    crowd = Crowd(motor, seed=seed)
    shapes = torch.randn(2, SHAPE_DIM, generator=torch.Generator().manual_seed(4))
    ids = [crowd.spawn(shape=shapes[k], position=(2.0 * k, 0.0)) for k in range(2)]
    return crowd, ids


def test_reset_stands_the_avatar_up_where_it_is_with_no_goal(motor):
    crowd, (i, j) = _shaped_crowd(motor, 1)
    crowd.set_goal(i, (1.0, 0.5))
    crowd.step_segment()
    crowd.push(i, "head", (0.0, 0.0, 3.0))
    crowd.refill(1)
    before, other = crowd.state(i).clone(), crowd.state(j).clone()
    crowd.reset(i)
    x = crowd.state(i)
    assert torch.equal(x, standing_state(crowd.shape(i), (float(before[0]), float(before[2]))))
    assert float(body_mismatch(x.double(), rest_offsets(crowd.shape(i), torch.float64)).max()) < 1e-5
    a = crowd.avatars[i]
    assert crowd.goal_velocity(i) is None and a.facing_goal is None and a.pending_velocity is None and a.queue == []
    assert torch.equal(crowd.state(j), other) and len(crowd.avatars[j].queue) == 15  # the others go on
    with pytest.raises(KeyError, match="no avatar 9"):
        crowd.reset(9)


def test_reseed_continues_as_a_crowd_freshly_seeded_so(motor):
    crowd, ids = _shaped_crowd(motor, 1)
    crowd.set_goal(ids[1], (1.0, 0.0))
    crowd.step_segment()  # the noise streams have moved on
    crowd.reseed(7)
    fresh = Crowd(motor, seed=7)
    assert [fresh.spawn(crowd.state(i), crowd.shape(i)) for i in ids] == ids
    fresh.set_goal(ids[1], (1.0, 0.0))
    for _ in range(2):
        a, b = crowd.step_segment(), fresh.step_segment()
        assert all(torch.equal(a[i], b[i]) for i in ids)
    assert crowd.seed == 7 and crowd.spawn() == fresh.spawn() == 2
    assert torch.equal(crowd.step_segment()[2], fresh.step_segment()[2])  # later spawns use the new seed


def test_advance_shows_one_queued_frame_and_holds_the_stalled(motor):
    crowd, (i, j) = _shaped_crowd(motor, 1)
    assert crowd.ids() == [i, j] and len(crowd) == 2 and j in crowd and 5 not in crowd
    crowd.refill(1)
    assert not crowd.needs_frames(15) and crowd.needs_frames(16)
    crowd.interrupt(j)
    head, held = crowd.avatars[i].queue[0], crowd.state(j)
    shown, stalled = crowd.advance()
    assert shown[i] is head and crowd.state(i) is head and len(crowd.avatars[i].queue) == 14
    assert stalled == [j] and shown[j] is held and crowd.state(j) is held
    assert crowd.needs_frames(1)


@pytest.mark.parametrize("B", [1, 4])
def test_guidance_gradients_match_autograd(B):
    g = torch.Generator().manual_seed(0)
    x = torch.randn(B, 15, 267, generator=g, dtype=torch.float64, requires_grad=True)
    v = torch.randn(B, 3, generator=g, dtype=torch.float64)
    r = torch.nn.functional.normalize(torch.randn(B, 3, generator=g, dtype=torch.float64) * torch.tensor([1.0, 0, 1.0], dtype=torch.float64), dim=-1)
    for fn, goal in ((move_loss_and_grad, v), (facing_loss_and_grad, r)):
        loss, grad = fn(x, goal)
        auto, = torch.autograd.grad(loss.sum(), x)
        assert torch.allclose(grad, auto, atol=1e-9), fn.__name__


def test_bad_arguments_are_named(motor, tmp_path):
    crowd = Crowd(motor)
    i = crowd.spawn()
    with pytest.raises(ValueError, match="unknown impulse preset 'moonwalk'.*presets are"):
        crowd.impulse(i, "moonwalk")
    with pytest.raises(ValueError, match="goal velocity.*finite"):
        crowd.set_goal(i, (math.nan, 0.0))
    with pytest.raises(KeyError, match="no avatar 7"):
        crowd.push(7, "head", (0, 0, 1))
    with pytest.raises(ValueError, match="unknown joint"):
        crowd.push(i, "tail", (0, 0, 1))
    from avatar_motor.cli import main
    bad = tmp_path / "bad.bvh"
    bad.write_text("HIERARCHY\nROOT x\n{")
    assert main(["generate", "--model", str(tmp_path / "tiny"), "--init", str(bad), "--out", str(tmp_path / "o.bvh")]) == 2
    assert main(["generate", "--model", str(tmp_path / "tiny"), "--impulse", "nope@1", "--out", str(tmp_path / "o.bvh")]) == 2
    assert main(["generate", "--model", str(tmp_path / "tiny"), "--goal", "nan,0", "--out", str(tmp_path / "o.bvh")]) == 2
    assert not (tmp_path / "o.bvh").exists()


def test_presets_follow_table_a1():
    names = {"left_kick", "right_kick", "forward_run", "back_flip", "forward_roll"}
    assert set(IMPULSE_PRESETS) == names
    from avatar_motor.body.skeleton import JOINT_INDEX, MIRROR
    # the kicks (retuned): the kicking leg's knee, ankle and foot, up and forward; mirror images
    P = IMPULSE_PRESETS
    assert P["right_kick"].joints == [JOINT_INDEX[f"right_{j}"] for j in ("knee", "ankle", "foot")]
    assert P["left_kick"].joints == [MIRROR[j] for j in P["right_kick"].joints]
    assert P["left_kick"].velocity == P["right_kick"].velocity == (0.0, 0.5, 0.5)
    # the roll (retuned): the upper trunk dives with the head, shoulders and elbows
    assert JOINT_INDEX["spine3"] in P["forward_roll"].joints and P["forward_roll"].velocity == (0.0, -0.5, 0.5)
    # the others as in the table
    assert (P["back_flip"].joints, P["back_flip"].velocity) == ([JOINT_INDEX["head"]], (0.0, 0.0, -1.0))
    # the acrobatics start from a stance; the run keeps the body's momentum
    assert [n for n in sorted(P) if P[n].stance] == ["back_flip", "forward_roll", "left_kick", "right_kick"]


def test_an_acrobatic_preset_takes_the_bodys_horizontal_momentum_away(motor):
    from avatar_motor.body.motion_state import SLICES, velocities_of
    moving = torch.tensor([1.2, -0.3, 0.4])  # a walking body (and some vertical motion, which stays)
    x = standing_state()
    x[SLICES["velocities"]] = moving.repeat(22)
    for preset, stance in (("right_kick", True), ("forward_run", False)):
        crowd = Crowd(motor, seed=0)
        i = crowd.spawn(x.clone())
        crowd.impulse(i, preset)
        batch = crowd.prepare(10**6)
        p = IMPULSE_PRESETS[preset]
        others = [j for j in range(22) if j not in p.joints]
        after = velocities_of(batch.x0[0]) + batch.impulse_velocity[0]
        if stance:  # every joint the preset does not push is left with the vertical motion only
            assert torch.allclose(after[others], torch.tensor([0.0, -0.3, 0.0], dtype=torch.float64).expand(len(others), 3), atol=1e-6)
        else:
            assert torch.equal(batch.impulse_velocity[0, others], torch.zeros(len(others), 3, dtype=torch.float64))
        assert not crowd.avatars[i].pending_stance


@pytest.mark.parametrize("ext", ["bvh", "npz", "glb"])
def test_generate_files_reimport(motor, tmp_path, ext):
    from avatar_motor.cli import main
    out = tmp_path / f"m.{ext}"
    assert main(["generate", "--model", str(tmp_path / "tiny"), "--seconds", "1", "--init",
                 "tests/fixtures/walk_mixamo.bvh:5", "--impulse", "left_kick@0.3", "--out", str(out)]) == 0
    if ext == "bvh":
        from avatar_motor.data.retarget import retarget
        from avatar_motor.io.bvh import read_bvh
        r = retarget(read_bvh(out), ground="keep")
        assert r.info["skeleton"] == "smpl" and r.root_pos.shape == (30, 3)
        from avatar_motor.io.export import read_npz_states  # noqa: F401
    elif ext == "npz":
        from avatar_motor.io.export import read_npz_states
        X, fps, _ = read_npz_states(out)
        assert X.shape == (30, 267) and fps == 30
    else:
        from avatar_motor.io.gltf import read_glb
        doc, _ = read_glb(out)
        assert doc["asset"]["version"] == "2.0" and doc["animations"][0]["channels"]


def test_smoothing_removes_frame_noise_and_keeps_the_join():
    from avatar_motor.eval.metrics import jitter
    from avatar_motor.runtime.processing import smooth_segment
    x = walk_states()
    x0, seg = x[:, 0], x[:, 1:]
    noisy = seg.clone()
    noisy[..., 135:201] += torch.randn(noisy[..., 135:201].shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 0.005
    out = smooth_segment(x0, noisy, 1.0)
    full = lambda s: joints_of(torch.cat((x0[:, None], s), 1))  # noqa: E731
    assert jitter(full(out)) < 0.3 * jitter(full(noisy))
    assert (joints_of(out) - joints_of(seg)).abs().mean() < 0.01  # the motion itself is kept
    assert torch.allclose(velocities_of(out)[:, 0], (joints_of(out)[:, 0] - joints_of(x0)) * FPS)
    assert torch.equal(smooth_segment(x0, noisy, 0.0), noisy)


def test_mirrored_rotations_give_mirrored_joints():
    from avatar_motor.body.skeleton import MIRROR
    from avatar_motor.eval.metrics import mirror_local_rotations
    x = walk_states()[0]
    u = unpack(x)
    off = rest_offsets(None, torch.float64)
    Mx = torch.diag(torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64))
    J, _ = forward_kinematics(u.root_pos * torch.tensor([-1.0, 1, 1], dtype=torch.float64), Mx @ u.root_rot @ Mx,
                              mirror_local_rotations(u.local_rot), off)
    assert torch.allclose(J[..., 0], -u.joints[:, MIRROR, 0], atol=1e-6)
    assert torch.allclose(J[..., 1:], u.joints[:, MIRROR, 1:], atol=1e-6)


def _slid(x: torch.Tensor, velocity=(0.4, 0.0, 0.0)) -> torch.Tensor:
    """States x (B, T, 267) with the whole body carried along at `velocity` m/s (a treadmill slide)."""
    from avatar_motor.body.motion_state import SLICES
    T = x.shape[1]
    d = torch.arange(T, dtype=x.dtype)[:, None] / FPS * torch.tensor(velocity, dtype=x.dtype)  # (T, 3)
    out = x.clone()
    out[..., SLICES["root_pos"]] += d
    out[..., SLICES["joints"]] += d.repeat(1, 22)
    out[..., SLICES["velocities"]] += torch.tensor(velocity, dtype=x.dtype).repeat(22)
    return out


def test_smoothing_keeps_constant_velocity_motion_exactly():
    from avatar_motor.runtime.processing import smooth_segment
    x = _slid(standing_state()[None, None].double().repeat(1, 16, 1), (0.8, 0.0, -0.3))
    out = smooth_segment(x[:, 0], x[:, 1:], 1.25)
    # the past continued at x0's velocity in front, the end point-reflected: a straight line stays
    # a straight line, so segments neither slow down at their ends nor kink at the joins
    assert torch.allclose(joints_of(out), joints_of(x[:, 1:]), atol=1e-9)


def test_velocity_fusion_removes_position_noise_and_keeps_clean_motion():
    from avatar_motor.runtime.processing import fuse_velocities
    x = walk_states()
    x0, seg = x[:, 0], x[:, 1:]
    assert torch.allclose(joints_of(fuse_velocities(x0, seg, 3.0)), joints_of(seg), atol=1e-9)
    noisy = seg.clone()
    noisy[..., 135:201] += torch.randn(noisy[..., 135:201].shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64) * 0.01
    out = fuse_velocities(x0, noisy, 3.0)
    err = lambda s: float((joints_of(s) - joints_of(seg)).norm(dim=-1).mean())  # noqa: E731
    assert err(out) < 0.6 * err(noisy)
    # the root travels with the pelvis
    assert torch.allclose(unpack(out).root_pos - joints_of(out)[..., 0, :], unpack(noisy).root_pos - joints_of(noisy)[..., 0, :])
    assert torch.equal(fuse_velocities(x0, noisy, 0.0), noisy)


def test_planted_feet_do_not_slide():
    from avatar_motor.eval.metrics import asr
    from avatar_motor.runtime.processing import lock_feet
    still = standing_state()[None, None].double().repeat(1, 16, 1)
    slid = _slid(still)  # standing feet carried at 0.4 m/s: pure skating
    out = lock_feet(slid[:, 0], slid[:, 1:])
    full = torch.cat((slid[:, :1], out), 1)
    assert asr(joints_of(slid)) == 1.0 and asr(joints_of(full)) == 0.0
    assert (joints_of(out) - joints_of(still[:, 1:])).abs().max() < 1e-9  # back where it stood
    # feet in the air (or fast) are not planted: a jump keeps its travel
    air = slid.clone()
    air[..., 136:201:3] += 0.5
    air[..., 1] += 0.5
    assert torch.allclose(lock_feet(air[:, 0], air[:, 1:]), air[:, 1:], atol=1e-9)


def test_a_body_twisting_on_both_planted_feet_pivots_instead_of_sliding():
    from avatar_motor.body.motion_state import apply_transform
    from avatar_motor.runtime.processing import lock_feet
    still = standing_state()[None, None].double().repeat(1, 16, 1)
    yaw = torch.arange(16, dtype=torch.float64) * 1.5 / FPS  # the whole body spins at 1.5 rad/s about its pelvis
    pel = joints_of(still)[0, 0, 0] * torch.tensor([1.0, 0.0, 1.0], dtype=torch.float64)
    R = rot.yaw_matrix(yaw)[None]  # (1, 16, 3, 3): one rotation per frame
    twist = apply_transform(still[:, :, None], R, (pel - (R @ pel[:, None])[..., 0]))[:, :, 0]
    feet = joints_of(twist)[..., [10, 11], :]
    assert float((feet[:, -1] - feet[:, 0]).norm(dim=-1).min()) > 0.05  # both feet slide
    out = lock_feet(twist[:, 0], twist[:, 1:], yaw=True)
    assert (joints_of(out)[..., [10, 11], :] - feet[:, :1]).norm(dim=-1).max() < 1e-6  # both stay put
    # translation alone cannot hold two feet that slide apart
    moved = (joints_of(lock_feet(twist[:, 0], twist[:, 1:]))[..., [10, 11], :] - feet[:, :1]).norm(dim=-1).max()
    assert moved > 0.05


def test_inertialization_matches_velocity_at_the_join():
    x = walk_states()
    x0, seg = x[:, 0], x[:, 1:].clone()
    seg[..., 135:201] += 0.02 * torch.arange(1, 16, dtype=seg.dtype)[:, None] * 30 / FPS  # a velocity mismatch
    out = inertialize(x0, seg, 0.2, match_velocity=torch.ones(2, dtype=torch.bool))
    v_first = (joints_of(out)[:, 0] - joints_of(x0)) * FPS
    plain = inertialize(x0, seg, 0.2)
    v_plain = (joints_of(plain)[:, 0] - joints_of(x0)) * FPS
    target = velocities_of(x0)
    assert (v_first - target).norm(dim=-1).mean() < 0.5 * (v_plain - target).norm(dim=-1).mean()


def test_a_steered_avatar_travels_with_the_processing_on(tmp_path):
    # foot locking must not pin an avatar that is being steered (the shipped model glides under guidance)
    crowd = Crowd(shipped_or_tiny(tmp_path), seed=0)
    ids = [crowd.spawn(position=(3.0 * k, 0.0)) for k in range(4)]
    for i in ids:
        crowd.set_goal(i, (0.0, 1.3))
    segs = [crowd.step_segment() for _ in range(8)]
    J = joints_of(torch.stack([torch.cat([s[i] for s in segs]) for i in ids]))
    assert float((J[:, -1, 0, 2] - J[:, 0, 0, 2]).mean()) > 1.0  # metres forward in 4 s


def test_a_goal_behind_turns_the_avatar_around(tmp_path):
    from avatar_motor.runtime.guidance import facing_of
    crowd = Crowd(shipped_or_tiny(tmp_path), seed=1)
    ids = [crowd.spawn(position=(3.0 * k, 0.0)) for k in range(4)]  # standing, facing +Z
    for i in ids:
        crowd.set_goal(i, (0.0, -1.0))
    for _ in range(6):
        out = crowd.step_segment()
    z, _ = facing_of(torch.stack([out[i][-1] for i in ids]))
    assert float(z[:, 2].mean()) < -0.5  # facing -Z after 3 s


def test_smoothing_width_can_differ_per_body():
    from avatar_motor.runtime.processing import smooth_segment
    x = walk_states()
    x0, seg = x[:, 0], x[:, 1:].clone()
    seg[..., 135:201] += torch.randn(seg[..., 135:201].shape, generator=torch.Generator().manual_seed(3), dtype=torch.float64) * 0.01
    both = smooth_segment(x0, seg, torch.tensor([0.0, 2.0], dtype=torch.float64))
    assert torch.allclose(joints_of(both[:1]), joints_of(seg[:1]), atol=1e-12)  # sigma 0: untouched
    assert torch.allclose(both[1:], smooth_segment(x0[1:], seg[1:], 2.0), atol=1e-12)
    # a body beside a wider-smoothed one is smoothed as it is alone (a crowd equals solo avatars)
    mixed = smooth_segment(x0, seg, torch.tensor([1.25, 3.0], dtype=torch.float64))
    assert torch.allclose(mixed[:1], smooth_segment(x0[:1], seg[:1], 1.25), atol=1e-12)


@pytest.mark.parametrize("with_body, expected", [(0.0, (-1.0, 0.0)), (1.0, (0.0, 1.0)), (0.5, (-0.7071, 0.7071))])
def test_steering_velocity_turns_with_the_body(motor, with_body, expected):
    # a standing body facing +Z told to go right (-X): steer_with_body rotates the body's steering
    # velocity from the goal back toward where the body faces, by that fraction of the angle
    from avatar_motor.runtime.crowd import RuntimeConfig
    from avatar_motor.runtime.sampler import STEER_JOINTS
    from avatar_motor.body.motion_state import SLICES
    crowd = Crowd(motor, RuntimeConfig(steer_impulse=1.0, turn_impulse=0.0, steer_with_body=with_body))
    x0 = standing_state()[None].double()
    x = x0.clone()
    goal = torch.tensor([-1.0, 0.0, 0.0])
    crowd.sampler._steer(x, [goal], [goal], torch.eye(3, dtype=torch.float64)[None])
    dv = (x - x0)[0, SLICES["velocities"]].view(22, 3)[STEER_JOINTS].mean(0)
    assert torch.allclose(dv[[0, 2]].float(), torch.tensor(expected), atol=1e-3)


def _wrapped(a: torch.Tensor) -> torch.Tensor:
    return torch.atan2(torch.sin(a), torch.cos(a))


def test_turning_toward_a_facing_goal_keeps_the_path_and_the_bones():
    from avatar_motor.body.skeleton import PARENTS
    from avatar_motor.body.motion_state import facing_yaw
    from avatar_motor.runtime.processing import turn_toward
    x = walk_states()
    x0, seg = x[:, 0], x[:, 1:]
    goal = facing_yaw(joints_of(seg[:, -1])) + torch.tensor([0.6, -3.0], dtype=seg.dtype)  # a small and a large turn
    out, added = turn_toward(x0, seg, goal, max_rate=math.pi, tolerance=0.1)
    yaw = facing_yaw(joints_of(out))
    assert torch.allclose(_wrapped(goal - yaw[:, -1])[0], torch.tensor(0.1, dtype=seg.dtype), atol=1e-9)  # up to the tolerance
    turned = _wrapped(yaw - facing_yaw(joints_of(seg)))
    assert torch.allclose(turned, added, atol=1e-9)  # the yaw it reports is the yaw it added
    assert float(torch.diff(turned, dim=1, prepend=torch.zeros(2, 1, dtype=seg.dtype)).abs().max()) <= math.pi / FPS + 1e-9
    assert float(turned[1, -1]) < -0.5  # the large turn goes on, capped
    J, J_in = joints_of(out), joints_of(seg)
    assert torch.allclose(J[..., 0, [0, 2]], J_in[..., 0, [0, 2]], atol=1e-12)  # the pelvis path is kept

    def bones(J):
        return (J[..., 1:, :] - J[..., PARENTS[1:], :]).norm(dim=-1)
    assert torch.allclose(bones(J), bones(J_in), atol=1e-12)
    assert torch.allclose(unpack(out).local_rot, unpack(seg).local_rot)
    assert torch.allclose(turn_toward(x0, seg, goal, math.pi, 0.1, where=torch.tensor([False, False]))[0], seg, atol=1e-12)


def test_a_standing_body_turns_within_the_rate_and_foot_locking_keeps_the_turn():
    from avatar_motor.body.motion_state import facing_yaw
    from avatar_motor.runtime.processing import lock_feet, turn_toward
    still = standing_state()[None, None].double().repeat(2, 16, 1)
    lifted = still.clone()
    lifted[1, -2:, 136:201:3] += 0.3  # the second body lifts everything (both feet) in the last 2 frames
    x0, seg = lifted[:, 0], lifted[:, 1:]
    goal = torch.full((2,), 1.5, dtype=torch.float64)
    out, added = turn_toward(x0, seg, goal, max_rate=math.pi)
    steps = torch.diff(added, dim=1, prepend=torch.zeros(2, 1, dtype=torch.float64))
    assert float(steps.abs().max()) <= math.pi / FPS + 1e-9  # no snap when the turn has few frames to happen in
    assert torch.allclose(steps[0], steps[0, :1].expand(15))  # planted all along: it turns evenly
    assert float(steps[1, :-2].abs().max()) < 1e-12  # it waits for the free frames
    locked = lock_feet(x0, out, yaw=True, turned=added)
    kept = _wrapped(facing_yaw(joints_of(locked[:, -1])) - facing_yaw(joints_of(seg[:, -1])))
    assert torch.allclose(kept[0], added[0, -1], atol=1e-9)  # the yaw lock does not undo the turn
    undone = _wrapped(facing_yaw(joints_of(lock_feet(x0, out, yaw=True)[:, -1])) - facing_yaw(joints_of(seg[:, -1])))
    assert float(undone[0].abs()) < 1e-6  # (without `turned` it would)


def test_commands_faster_than_segments_coalesce(motor):
    """A goal stream (a gamepad stick) must not cut the queue at every message: a goal within the
    recut tolerance only updates the controls; a real change keeps `keep_on_cut` frames (shown while
    the new segment is made) and cuts once; changes while that segment is made wait for it."""
    crowd = Crowd(motor, seed=0)
    crowd.keep_on_cut = 2
    i = crowd.spawn()
    a = crowd.avatars[i]
    crowd.set_goal(i, (0.0, 1.2))
    crowd.refill(8)
    assert a.epoch == 1 and not a.regenerating and len(a.queue) == 15
    head = list(a.queue)

    def same(q, h):
        return len(q) == len(h) and all(x is y for x, y in zip(q, h))
    for k in range(60):  # jitter of +-0.05 m/s: no cut, the latest goal is used by the next segment
        crowd.set_goal(i, (0.05 * (-1) ** k, 1.2 - 0.05 * (-1) ** k))
    assert a.epoch == 1 and same(a.queue, head) and torch.allclose(a.v_goal, torch.tensor([-0.05, 0.0, 1.25]))
    crowd.set_goal(i, (1.2, 0.0))  # a real change: two frames kept, the rest cut
    assert a.epoch == 2 and a.regenerating and same(a.queue, head[:2])
    crowd.set_goal(i, (-1.2, 0.0))  # while that segment is made: marked, no second cut
    crowd.push(i, "head", (0.0, 0.0, 1.0))
    assert a.epoch == 2 and a.recut and same(a.queue, head[:2])
    job = crowd.prepare(8)
    assert torch.equal(job.v_goal[0], a.v_goal) and bool(job.impulse[0])  # it uses the latest controls
    crowd.set_goal(i, (0.0, -1.2))  # changed again after the snapshot
    crowd.commit(job, crowd.compute(job))
    assert a.epoch == 3 and a.regenerating and not a.recut and len(a.queue) == 2  # committed, then cut once more
    job = crowd.prepare(8)
    crowd.commit(job, crowd.compute(job))
    assert a.epoch == 3 and not a.regenerating and len(a.queue) == 17
    crowd.set_goal(i, (0.0, -1.2))  # the same goal again: nothing to do
    assert a.epoch == 3 and len(a.queue) == 17
    # offline (keep_on_cut 0) a command shows at the next frame, as before
    crowd.keep_on_cut = 0
    crowd.set_goal(i, None)
    assert a.queue == [] and a.epoch == 4


def test_a_broken_model_is_never_streamed_the_guard_stands_the_avatar_up(tmp_path, caplog):
    """Weights scaled x1000 once put a pelvis at 352 km with no warning: the physical guard refuses
    such a segment, resets that avatar where it stood (the others go on) and says so, once."""
    import logging

    from avatar_motor.runtime.processing import physical_faults
    good = tiny_motor(tmp_path)
    broken = tiny_motor(tmp_path / "b")
    with torch.no_grad():
        for p in broken.net.parameters():
            p.mul_(1000.0)
    crowd = Crowd(broken, seed=0)
    i = crowd.spawn(position=(1.0, 2.0))
    start = crowd.state(i).clone()
    with caplog.at_level(logging.WARNING, logger="avatar_motor.runtime"):
        for _ in range(40):
            x = crowd.next_frames()[i]
            assert torch.isfinite(x).all() and 0.5 < float(x[1]) < 1.5 and abs(float(x[0]) - 1.0) < 1e-4
    assert crowd.guard_resets >= 20 and torch.equal(crowd.state(i), start)
    assert sum("not a physical body" in r.getMessage() for r in caplog.records) == 2  # the 1st and 10th, not 20+ lines
    # each invariant of the guard on its own, on a good segment made bad one way at a time
    c = Crowd(good, seed=0)
    j = c.spawn()
    seg = c.step_segment()[j].double()[None]
    x0, off = seg[:, 0].clone(), rest_offsets(torch.zeros(1, SHAPE_DIM), torch.float64)
    seg = seg[:, 1:]
    assert physical_faults(x0, seg, off) == [None]
    J = SLICES["joints"].start
    for edit, why in ((lambda s: s.__setitem__((0, 3, 5), float("nan")), "non-finite"),
                      (lambda s: s[0, :, J + 1].add_(5.0), "pelvis height"),
                      (lambda s: s[0, -1, J:J + 66:3].add_(20.0), "pelvis moved"),
                      (lambda s: s[0, 2, J + 3 * 15:J + 3 * 15 + 3].add_(0.3), "bone")):
        bad = seg.clone()
        edit(bad)
        assert why in physical_faults(x0, bad, off)[0]
    # the pelvis height is above the ground under it: on a ground tilted 2 m down it is a body
    low = seg.clone()
    low[0, :, J + 1:J + 66:3] -= 2.0
    assert "pelvis height" in physical_faults(x0, low, off)[0]
    assert physical_faults(x0, low, off, torch.full(low.shape[:2], -2.0, dtype=torch.float64)) == [None]


def test_a_kick_is_counted_only_while_standing():
    """eval impulses' kick detector: the ankle above the knee with the pelvis up and the trunk
    upright; the same leg raised by a body lying on its back is no kick."""
    from avatar_motor.body.skeleton import JOINT_INDEX
    from avatar_motor.eval.control import impulse_success
    X = standing_state()[None, None].repeat(1, 45, 1)
    J = X[..., SLICES["joints"]].view(1, 45, 22, 3)
    ank, kn = JOINT_INDEX["right_ankle"], JOINT_INDEX["right_knee"]
    J[:, 20, ank, 1] = J[:, 20, kn, 1] + 0.1  # the foot kicked up in one frame
    assert impulse_success("right_kick", X).item() and not impulse_success("left_kick", X).item()
    lying = X.clone()
    Jl = lying[..., SLICES["joints"]].view(1, 45, 22, 3)
    Jl[..., 1] = Jl[..., 1] * 0.2 + 0.1  # everything near the ground: pelvis at about 0.3 m
    Jl[:, 20, ank, 1] = Jl[:, 20, kn, 1] + 0.1
    assert not impulse_success("right_kick", lying).item()


def _walk_with_past(T=24):
    """A procedural walk split at frame PAST: (past (2, PAST, 267), x0 (2, 267), the rest)."""
    from avatar_motor.runtime.processing import PAST
    x = walk_states(T)
    return x[:, :PAST], x[:, PAST], x[:, PAST + 1:]


def test_the_past_leads_into_x0_only_when_it_is_the_frames_before():
    from avatar_motor.runtime.processing import continuous_past
    past, x0, _ = _walk_with_past()
    yes = torch.ones(2, dtype=torch.bool)
    assert continuous_past(x0, past, yes).all()
    assert not continuous_past(x0, past, ~yes).any()  # the avatar has no such past
    moved = x0.clone()
    moved[:, SLICES["joints"]] += 0.5  # a body put elsewhere (reset, stood up): its past is not its own
    assert not continuous_past(moved, past, yes).any()


def test_smoothing_reads_the_frames_shown_before_the_join():
    from avatar_motor.runtime.processing import PAST, smooth_segment
    x = walk_states(24)
    past, x0, seg = x[:, :PAST], x[:, PAST], x[:, PAST + 1:]
    yes = torch.ones(2, dtype=torch.bool)
    # the walk smoothed in one piece: its frames after the join saw the real frames before it
    whole = smooth_segment(x[:, 0], x[:, 1:], 1.25)[:, PAST:PAST + 4]
    with_past = smooth_segment(x0, seg, 1.25, past, yes)[:, :4]
    # a join is no different from any frame (but for the first velocity: a difference from the
    # x0 shown, where the whole walk has x0 smoothed too)
    assert torch.allclose(with_past[..., :SLICES["velocities"].start], whole[..., :SLICES["velocities"].start], atol=1e-9)
    assert torch.allclose(with_past[:, 1:], whole[:, 1:], atol=1e-9)
    held = smooth_segment(x0, seg, 1.25)[:, :4]  # x0 extrapolated, its rotations held
    assert float((joints_of(held) - joints_of(whole)).norm(dim=-1).max()) > 1e-4
    assert torch.equal(smooth_segment(x0, seg, 1.25, past, ~yes), smooth_segment(x0, seg, 1.25))


def test_inertialization_matches_the_upper_body_turn_at_the_join():
    from avatar_motor.body.skeleton import JOINT_INDEX
    past, x0, seg = _walk_with_past()
    u = unpack(seg)
    arm = JOINT_INDEX["left_shoulder"] - 1  # local_rot index
    knee = JOINT_INDEX["left_knee"] - 1
    local = u.local_rot.clone()
    spin = rot.axis_angle_to_matrix(torch.tensor([0.0, 0.0, 1.0], dtype=seg.dtype) * 0.08 * torch.arange(1, 16, dtype=seg.dtype)[:, None])
    local[:, :, arm] = spin @ local[:, :, arm]  # the new motion swings the arm at 2.4 rad/s more ...
    local[:, :, knee] = spin @ local[:, :, knee]  # ... and the knee
    new = pack(u.root_pos, u.root_rot, local, u.joints, u.velocities)
    yes = torch.ones(2, dtype=torch.bool)

    def first_turn(out, j):  # the rotation's turn from x0 to the first frame, rad
        return rot.matrix_to_axis_angle(unpack(out).local_rot[:, 0, j] @ unpack(x0).local_rot[:, j].transpose(-1, -2)).norm(dim=-1)

    x0_turn = rot.matrix_to_axis_angle(unpack(x0).local_rot[:, arm] @ unpack(past[:, -1]).local_rot[:, arm].transpose(-1, -2)).norm(dim=-1)
    matched = inertialize(x0, new, 0.2, match_velocity=yes, before=past[:, -1], has_before=yes)
    plain = inertialize(x0, new, 0.2, match_velocity=yes)
    # the arm keeps turning as it did before the join; without the frame before it jumps to the new rate
    assert float((first_turn(matched, arm) - x0_turn).abs().max()) < 0.01
    assert float((first_turn(plain, arm) - x0_turn).abs().max()) > 0.05
    # legs are blended in position only, with or without it (see _TURN_MATCHED)
    assert torch.allclose(unpack(matched).local_rot[..., knee, :, :], unpack(plain).local_rot[..., knee, :, :], atol=1e-12)
    # a pushed body (match_velocity false) keeps its new motion's turn
    pushed = inertialize(x0, new, 0.2, match_velocity=~yes, before=past[:, -1], has_before=yes)
    assert torch.allclose(pushed, inertialize(x0, new, 0.2, match_velocity=~yes), atol=1e-12)


def test_inertialization_matches_the_root_turn_of_a_body_without_a_facing_goal():
    past, x0, seg = _walk_with_past()
    u = unpack(seg)
    spin = rot.axis_angle_to_matrix(torch.tensor([0.0, 1.0, 0.0], dtype=seg.dtype) * 0.08 * torch.arange(1, 16, dtype=seg.dtype)[:, None])
    new = pack(u.root_pos, spin @ u.root_rot, u.local_rot, u.joints, u.velocities)  # the new motion spins about y
    yes = torch.ones(2, dtype=torch.bool)
    free = torch.tensor([True, False])  # the second body turns toward a facing goal

    def first_turn(out):  # the root's turn from x0 to the first frame, rad
        return rot.matrix_to_axis_angle(unpack(out).root_rot[:, 0] @ unpack(x0).root_rot.transpose(-1, -2)).norm(dim=-1)

    x0_turn = rot.matrix_to_axis_angle(unpack(x0).root_rot @ unpack(past[:, -1]).root_rot.transpose(-1, -2)).norm(dim=-1)
    out = inertialize(x0, new, 0.2, match_velocity=yes, before=past[:, -1], has_before=yes, turn_root=free)
    plain = inertialize(x0, new, 0.2, match_velocity=yes, before=past[:, -1], has_before=yes)
    # the free body's root keeps turning as it did before the join (to within the spring's curvature
    # over one frame, ~0.02 rad for this 2.4 rad/s change); the steered one's jumps to the new rate
    assert float((first_turn(out)[0] - x0_turn[0]).abs()) < 0.025
    assert float((first_turn(out)[1] - x0_turn[1]).abs()) > 0.05
    assert torch.allclose(out[1], plain[1], atol=1e-12)
    # a body with no past frames has no turn to match
    assert torch.allclose(inertialize(x0, new, 0.2, match_velocity=yes, before=past[:, -1], has_before=~yes, turn_root=free),
                          inertialize(x0, new, 0.2, match_velocity=yes), atol=1e-12)


def test_the_runtime_hands_the_frames_shown_to_the_join(motor):
    from avatar_motor.runtime.processing import PAST
    crowd = Crowd(motor, seed=0)
    i = crowd.spawn()
    assert not bool(crowd.prepare(1).has_past[0])  # just spawned: no past
    shown = [crowd.next_frames()[i].clone() for _ in range(PAST + 20)]
    crowd._trim(crowd.avatars[i], 0)  # the queue cut: the next segment continues the frame shown
    batch = crowd.prepare(1)
    assert bool(batch.has_past[0])
    assert torch.equal(batch.x0[0], shown[-1].double())
    assert torch.equal(batch.past[0], torch.stack(shown[-PAST - 1:-1]).double())
    crowd.reset(i)  # stood up elsewhere: the past is not its own
    assert not bool(crowd.prepare(1).has_past[0])


def test_traced_stages_equal_the_python_stages_on_other_batches(tmp_path):
    """runtime/stage_graph.py: a graph traced on one batch gives, bit for bit, what the Python
    stages give on batches of other sizes and contents (goals, facing, an impulse, a past or not),
    for the default stages and other choices of them."""
    import dataclasses
    from avatar_motor.runtime import stage_graph
    from avatar_motor.runtime.crowd import RuntimeConfig
    from avatar_motor.runtime.stages import StageContext, run_stages
    crowd = Crowd(shipped_or_tiny(tmp_path), RuntimeConfig(backend="torch", trace_stages=False), seed=3)
    for _ in range(5):
        crowd.spawn()
    crowd.set_goal(1, velocity=(1.0, 0.3), facing=(1.0, 0.0))
    crowd.set_goal(3, facing=(0.0, -1.0))
    seen = []
    real = crowd._stages
    crowd._stages = lambda ctx, seg: (seen.append((StageContext(**{**ctx.__dict__, "turned": None}), seg)),
                                      real(ctx, seg))[1]
    crowd.step_segment()
    crowd.impulse(2, "forward_run")
    crowd.step_segment()
    ctx, seg = seen[-1]
    assert ctx.any_facing and ctx.past is not None and not bool(ctx.match_velocity.all()) and bool(ctx.steered.any())

    def rows(c: StageContext, r: list[int]) -> StageContext:
        pick = lambda t: None if t is None else t[torch.tensor(r)]  # noqa: E731
        return StageContext(pick(c.x0), pick(c.offsets), pick(c.steered), pick(c.facing), pick(c.has_facing),
                            pick(c.lock_where), pick(c.lock_yaw), pick(c.match_velocity), pick(c.past),
                            pick(c.has_past), any_facing=c.any_facing)

    for stages in (crowd.cfg.stages, (), ("turn_toward", "lock_feet", "fk"), ("smooth", "inertialize", "leg_ik")):
        cfg = dataclasses.replace(crowd.cfg, stages=stages)
        for past in (True, False):  # the runtime's stages, and those of physics mode's candidates (no past)
            c = ctx if past else StageContext(**{**ctx.__dict__, "past": None, "has_past": None})
            graph = stage_graph.trace_stages(cfg, rows(c, [3]), seg[[3]])  # traced on one avatar
            for r in ([0, 1, 2, 3, 4], [2], [4, 1], [1, 1, 0]):
                want = run_stages(cfg, rows(c, r), seg[r])
                got = graph(*stage_graph._tensors(rows(c, r), seg[r]))
                assert torch.equal(got, want), (stages, past, r, float((got - want).abs().max()))
    # the runtime with traced stages streams the same frames as without
    frames = {}
    for traced in (False, True):
        cr = Crowd(shipped_or_tiny(tmp_path), RuntimeConfig(backend="torch", trace_stages=traced), seed=5)
        for _ in range(3):
            cr.spawn()
        cr.set_goal(0, velocity=(0.8, 0.0), facing=(0.0, 1.0))
        frames[traced] = [cr.step_segment() for _ in range(3)]
    for a, b in zip(frames[False], frames[True]):
        assert all(torch.equal(a[i], b[i]) for i in a)
