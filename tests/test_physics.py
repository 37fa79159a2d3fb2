"""The physics room (DROP's projective-dynamics body): each energy's projection, the factored
solve against a dense one, momentum without energies, gravity, standing on the ground, a push's
response, and the one body made of solved particles."""
import json

import numpy as np

import pytest
import torch

from avatar_motor.body import rotations as rot
from avatar_motor.body.motion_state import unpack
from avatar_motor.body.skeleton import JOINT_INDEX, NUM_JOINTS, PARENTS, forward_kinematics, rest_offsets
from avatar_motor.physics.solver import (BONES, H, MASS_SHARE, REST_HEIGHT, Candidates, PhysicsConfig, inertial_target,
                                         ballistic_candidates, pose_from_particles, prepare, project_bones,
                                         project_ground, project_prior, rigid_part, solve_global, step)
from avatar_motor.runtime.crowd import standing_state


def _standing(B: int = 1):
    x = standing_state().to(torch.float64)
    u = unpack(x[None].expand(B, -1))
    return u.joints.clone(), u.root_rot, u.local_rot, rest_offsets(None, torch.float64).expand(B, NUM_JOINTS, 3)


def _held(x, root, local) -> Candidates:
    """One candidate per body: the given pose (the prior wants it to stay)."""
    return Candidates(x[:, None], root[:, None], local[:, None])


def test_masses_are_a_body():
    assert abs(float(MASS_SHARE.sum()) - 1.0) < 1e-12 and bool((MASS_SHARE > 0).all())
    for name in ("hip", "knee", "ankle", "foot", "shoulder", "elbow", "wrist", "collar"):
        assert MASS_SHARE[JOINT_INDEX[f"left_{name}"]] == MASS_SHARE[JOINT_INDEX[f"right_{name}"]]
    legs = sum(float(MASS_SHARE[JOINT_INDEX[f"{s}_{n}"]]) for s in ("left", "right") for n in ("hip", "knee", "ankle", "foot"))
    assert 0.3 < legs < 0.4  # thighs, shanks and feet: about a third of the body


def test_config_errors_name_the_field():
    for bad, word in ((dict(mass=0.0), "mass"), (dict(iterations=0), "iterations"), (dict(contact=-1.0), "contact"),
                      (dict(kinematic=float("nan")), "kinematic")):
        with pytest.raises(ValueError, match=word):
            prepare(rest_offsets()[None], PhysicsConfig(**bad))


def test_projections():
    x, _, _, off = _standing(2)
    rest = off[:, 1:].norm(dim=-1)
    stretched = x * 1.3
    d = project_bones(stretched, rest)
    assert torch.allclose(d.norm(dim=-1), rest)
    v = stretched[:, BONES[:, 1]] - stretched[:, BONES[:, 0]]
    assert torch.allclose(rot.normalize(d), rot.normalize(v))  # directions kept
    # ground: the sunk joint goes up to its resting height where it stood the frame before
    prev = x.clone()
    sunk = x.clone()
    f = JOINT_INDEX["left_foot"]
    sunk[0, f] += torch.tensor([0.05, -0.1, 0.03], dtype=torch.float64)
    p = project_ground(sunk, prev)
    assert torch.allclose(p[0, f], torch.tensor([prev[0, f, 0], REST_HEIGHT[f], prev[0, f, 2]], dtype=torch.float64))
    above = sunk[..., 1] > REST_HEIGHT + 1e-9
    assert not above[0, f] and int(above.sum()) >= 2 * NUM_JOINTS - 4  # the feet stand at their height
    assert torch.equal(p[above], sunk[above])  # above the ground: no energy
    # the prior: the nearest candidate, in the energy's mass-weighted distance
    cands = torch.stack((x + 0.3, x + 0.01, x - 0.2), 1)
    near, k = project_prior(x, cands, prepare(off).masses)
    assert k.tolist() == [1, 1] and torch.equal(near, cands[:, 1])


def test_ground_contact_of_a_compliant_body_obeys_coulomb():
    """A sunk joint is held where it was while its slip along the ground is within friction times
    its depth (the cone); beyond, it keeps the slip past that; calm bodies and friction=None hold."""
    x, _, _, off = _standing(3)
    f = JOINT_INDEX["left_foot"]
    prev = x.clone()
    moved = x.clone()
    depth = 0.01  # under its resting height
    moved[:, f, 1] = REST_HEIGHT[f] - depth
    moved[0, f, 0] += 0.005  # within 0.8 x 1 cm: sticks
    moved[1, f, 0] += 0.03  # beyond: slides, 3 - 0.8 cm kept
    moved[2, f, 0] += 0.03  # the same slip, a calm body: held
    mu = torch.tensor([0.8, 0.8, float("inf")], dtype=torch.float64)
    p = project_ground(moved, prev, friction=mu)
    assert torch.allclose(p[:, f, 1], REST_HEIGHT[f].expand(3).double())
    assert abs(float(p[0, f, 0] - prev[0, f, 0])) < 1e-12
    assert abs(float(p[1, f, 0] - prev[1, f, 0]) - (0.03 - 0.8 * depth)) < 1e-12
    assert abs(float(p[2, f, 0] - prev[2, f, 0])) < 1e-12
    static = torch.full((3,), float("inf"), dtype=torch.float64)
    assert torch.equal(project_ground(moved, prev)[:, f], project_ground(moved, prev, friction=static)[:, f])
    above = moved[..., 1] > REST_HEIGHT + 1e-9
    assert torch.equal(p[above], moved[above])  # above the ground: no energy, whatever the friction
    # the pull back along the ground is at most friction times the push up, on the contact's force
    pulled, pushed = (prev[1, f] - moved[1, f])[[0, 2]], float(p[1, f, 1] - moved[1, f, 1])
    assert float((p[1, f] - moved[1, f])[[0, 2]].norm()) <= 0.8 * pushed + 1e-12 < float(pulled.norm())
    b = prepare(off, PhysicsConfig(friction=0.6), torch.tensor([False, True, False]))
    assert b.friction.tolist() == [0.6, float("inf"), 0.6]


def test_factored_solve_equals_a_dense_66_by_66_solve():
    torch.manual_seed(0)
    x, _, _, off = _standing(3)
    cfg = PhysicsConfig(rigidity=20.0, contact=2.0, range_of_motion=1.5, kinematic=4.0, kinematic_calm=25.0)
    calm = torch.tensor([False, True, False])  # the middle body is calm: its own kinematic weight
    b = prepare(off, cfg, calm)
    assert b.kinematic.tolist() == [4.0, 25.0, 4.0]
    assert torch.allclose(b.factor @ b.factor.transpose(-1, -2), b.matrix)
    y, kin, ground, ranged = (x + 0.05 * torch.randn_like(x) for _ in range(4))
    bones = project_bones(x + 0.02 * torch.randn_like(x), b.rest)
    got = solve_global(b, y, bones, ground, ranged, kin, cfg)
    for i in range(3):  # the energy written out over all 66 coordinates, minimised densely
        m = b.masses[i].repeat_interleave(3) / H**2  # x laid out joint-major: (x0, y0, z0, x1, ...)
        w_kin = cfg.kinematic_calm if calm[i] else cfg.kinematic
        A = torch.diag(m * (1 + cfg.contact + cfg.range_of_motion + w_kin))
        rhs = m * (y[i].flatten() + cfg.contact * ground[i].flatten() + cfg.range_of_motion * ranged[i].flatten()
                   + w_kin * kin[i].flatten())
        for n, (p, c) in enumerate(BONES.tolist()):
            w = cfg.rigidity * min(float(b.masses[i, p]), float(b.masses[i, c])) / H**2
            S = torch.zeros(3, 66, dtype=torch.float64)
            S[:, 3 * c:3 * c + 3] = torch.eye(3)
            S[:, 3 * p:3 * p + 3] = -torch.eye(3)
            A += w * S.T @ S
            rhs += w * S.T @ bones[i, n]
        dense = torch.linalg.solve(A, rhs).reshape(NUM_JOINTS, 3)
        assert torch.allclose(got[i], dense, atol=1e-10)


def test_momentum_is_conserved_without_forces_and_energies():
    """Bones only (internal forces), no gravity, ground or prior: the total linear momentum stays."""
    torch.manual_seed(1)
    x, root, local, off = _standing(2)
    cfg = PhysicsConfig(contact=0.0, range_of_motion=0.0, kinematic=0.0, gravity=0.0)
    b = prepare(off, cfg)
    v = torch.randn_like(x)
    p0 = (b.masses[..., None] * v).sum(1)
    for _ in range(30):
        x, v, _ = step(b, x, v, _held(x, root, local), cfg=cfg)
    assert torch.allclose((b.masses[..., None] * v).sum(1), p0, atol=1e-9)
    # and the bones held their lengths through the tumbling
    lengths = (x[:, BONES[:, 1]] - x[:, BONES[:, 0]]).norm(dim=-1)
    assert float((lengths - b.rest).abs().max()) < 0.02


def test_free_fall_is_gravity():
    x, root, local, off = _standing()
    x = x + torch.tensor([0.0, 5.0, 0.0], dtype=torch.float64)  # high above the ground
    cfg = PhysicsConfig(contact=0.0, range_of_motion=0.0, kinematic=0.0)
    b = prepare(off, cfg)
    v = torch.zeros_like(x)
    for _ in range(15):
        x, v, _ = step(b, x, v, _held(x, root, local), cfg=cfg)
    assert torch.allclose(v[..., 1], torch.full_like(v[..., 1], -15 * H * cfg.gravity), atol=1e-9)  # implicit Euler
    assert torch.allclose(v[..., [0, 2]], torch.zeros_like(v[..., [0, 2]]), atol=1e-9)


def test_a_body_held_by_its_prior_stands_and_a_push_moves_it_by_its_size():
    """Candidates = the standing pose: gravity, ground and prior balance, nothing sinks. A force
    at the pelvis for one frame moves the body its way, farther for a larger push."""
    x0, root, local, off = _standing()
    cfg = PhysicsConfig()
    b = prepare(off, cfg)
    held = _held(x0, root, local)
    x, v = x0.clone(), torch.zeros_like(x0)
    for _ in range(60):
        x, v, _ = step(b, x, v, held, cfg=cfg)
    assert float((x - x0).norm(dim=-1).max()) < 0.02
    assert float((x[..., 1] - REST_HEIGHT).min()) > -0.02  # no joint into the ground
    moved = []
    for push in (50.0, 100.0, 200.0):  # N s at the pelvis, forward (+z)
        f = torch.zeros_like(x0)
        f[:, 0, 2] = push / H  # the impulse delivered over one frame
        x, v = x0.clone(), torch.zeros_like(x0)
        x, v, _ = step(b, x, v, held, forces=f, cfg=cfg)
        path = [float(x[0, 0, 2] - x0[0, 0, 2])]
        for _ in range(5):
            x, v, _ = step(b, x, v, held, cfg=cfg)
            path.append(float(x[0, 0, 2] - x0[0, 0, 2]))
        moved.append(max(path))
        # the prior, which wants to stand, takes the pelvis back within a few frames
        assert path[-1] < 0.5 * max(path)
    assert 0.03 < moved[0] < moved[1] < moved[2], moved


def _momenta(x, v, masses):
    """Linear momentum (B, 3) and angular momentum about the centre of mass (B, 3)."""
    m = masses[..., None]
    com = (m * x).sum(1) / m.sum(1)
    return (m * v).sum(1), (m * torch.linalg.cross(x - com[:, None], v)).sum(1)


def test_the_rigid_part_of_a_displacement_carries_all_its_net_force_and_torque():
    torch.manual_seed(3)
    x, _, _, off = _standing(2)
    masses = prepare(off).masses
    d = 0.05 * torch.randn_like(x)
    rest = d - rigid_part(d, x, masses)
    force, torque = _momenta(x, rest, masses)  # d as a velocity: its momenta are its net force and torque
    assert torch.allclose(force, torch.zeros_like(force), atol=1e-12) and torch.allclose(torque, torch.zeros_like(torque), atol=1e-9)
    # a rigid motion (a shift and a small turn about any point) is all rigid part
    w, t = torch.tensor([0.01, -0.02, 0.015], dtype=torch.float64), torch.tensor([0.03, 0.0, -0.01], dtype=torch.float64)
    rigid = t + torch.linalg.cross(w.expand_as(x), x - x[:, :1])
    assert torch.allclose(rigid_part(rigid, x, masses), rigid, atol=1e-12)


def test_a_body_in_the_air_falls_whatever_its_prior_wants():
    """The prior wants the body to hover 2 m up: in flight (no joint touching the ground) a
    compliant body still falls as gravity has it, while the prior shapes it (here: turns it).
    With ballistic 0 (the prior's net force kept), or calm, it hovers."""
    x0, root, local, off = _standing()
    x0 = x0 + torch.tensor([0.0, 2.0, 0.0], dtype=torch.float64)
    turn = rot.axis_angle_to_matrix(torch.tensor([0.0, 0.3, 0.0], dtype=torch.float64))
    wanted = x0[:, :1] + ((x0 - x0[:, :1]) @ turn.T)
    held = Candidates(wanted[:, None], (turn @ root)[:, None], local[:, None])

    def fly(ballistic, calm=False):
        cfg = PhysicsConfig(ballistic=ballistic)
        b = prepare(off, cfg, torch.tensor([calm]))
        x, v = x0.clone(), torch.zeros_like(x0)
        for _ in range(8):  # as physics.segment steps it
            joints, flight = ballistic_candidates(b, x, v, held.joints, None, cfg)
            assert (flight is not None) == (ballistic > 0 and not calm)
            x, v, _ = step(b, x, v, Candidates(joints, held.root_rot, held.local_rot), cfg=cfg)
        return x, v, b.masses

    x, v, masses = fly(1.0)
    p, L = _momenta(x, v, masses)
    M = float(masses.sum())
    assert torch.allclose(p / M, torch.tensor([[0.0, -8 * H * 9.81, 0.0]], dtype=torch.float64), atol=1e-9)  # free fall
    assert float(L.norm()) > 0.05  # and the prior still turns it toward its pose
    for ballistic, calm in ((0.0, False), (1.0, True)):
        p_held, _ = _momenta(*fly(ballistic, calm))
        assert float(p_held[0, 1] / M) > -0.5, (ballistic, calm)  # held up: nowhere near -2.6 m/s


def test_inertial_target():
    x, _, _, off = _standing()
    b = prepare(off)
    v = torch.ones_like(x)
    f = torch.zeros_like(x)
    f[0, 3, 0] = 7.0
    y = inertial_target(x, v, f, b.masses, PhysicsConfig(gravity=10.0))
    want = x + H * v
    want[..., 1] -= 10.0 * H**2
    want[0, 3, 0] += H**2 * 7.0 / b.masses[0, 3]
    assert torch.allclose(y, want)


def test_the_solved_particles_become_one_body_with_the_samples_twist():
    x, root, local, off = _standing(2)
    # the sample's own joints: its own rotations come back, and the same joints
    r_pos, r_rot, r_local, J = pose_from_particles(x, root, local, off)
    assert torch.allclose(r_rot, root, atol=1e-6) and torch.allclose(r_local, local, atol=1e-6)
    assert torch.allclose(J, x, atol=1e-6)
    # particles bent: the left knee raised forward. The body follows the bones and stays rigid
    y = x.clone()
    knee, ankle, foot = JOINT_INDEX["left_knee"], JOINT_INDEX["left_ankle"], JOINT_INDEX["left_foot"]
    hip = JOINT_INDEX["left_hip"]
    R = rot.axis_angle_to_matrix(torch.tensor([-1.2, 0.0, 0.0], dtype=torch.float64))  # thigh forward and up
    for j in (knee, ankle, foot):
        y[:, j] = y[:, hip] + (R @ (x[:, j] - x[:, hip])[..., None])[..., 0]
    _, r_rot, r_local, J = pose_from_particles(y, root, local, off)
    J_fk, _ = forward_kinematics(y[:, 0], r_rot, r_local, off)
    assert torch.allclose(J, J_fk)  # one body: FK of the rotations it returns
    assert torch.allclose(J, y, atol=1e-6)  # a rigid bend is reached exactly
    # the twist about the thigh is the sample's: the local rotation differs by a swing only
    bones = (J[:, 1:] - J[:, PARENTS[1:]]).norm(dim=-1)
    assert torch.allclose(bones, off[:, 1:].norm(dim=-1))


def test_nnls_meets_its_optimality_conditions():
    import numpy as np
    from avatar_motor.physics.wrench import nnls
    rng = np.random.default_rng(0)
    for m, n in ((6, 8), (6, 40), (10, 4), (3, 3)):
        A, b = rng.normal(size=(m, n)), rng.normal(size=m)
        # cold, warm-started from the answer's own columns, and from a wrong guess: one solution
        x = nnls(A, b)
        for start in (x > 0, rng.random(n) < 0.5):
            assert np.allclose(nnls(A, b, start=start), x, atol=1e-9)
        g = A.T @ (A @ x - b)  # gradient of |Ax - b|^2 / 2
        assert (x >= 0).all()
        assert np.allclose(g[x > 0], 0, atol=1e-8) and (g[x == 0] >= -1e-8).all()
    # a b inside the cone of A's columns is met exactly
    A = np.abs(rng.normal(size=(6, 12)))
    c = np.abs(rng.normal(size=12))
    assert np.linalg.norm(A @ nnls(A, A @ c) - A @ c) < 1e-9


def test_root_wrench_metric_and_soft_correction_on_hand_made_cases():
    """Standing still on both feet: the ground explains everything (metric ~0). Held still in
    the air: the metric is the body's weight (the prior's "magic" force), and the correction
    with a large weight lets the body fall as gravity says; a small weight corrects less; below
    the skip threshold nothing moves."""
    import numpy as np
    from avatar_motor.physics.wrench import root_wrench, soft_correction
    x0, _, _, off = _standing()
    b = prepare(off)
    x, m = x0[0].numpy(), b.masses[0].numpy()
    v = np.zeros_like(x)
    feet = np.zeros(NUM_JOINTS, dtype=bool)
    feet[[JOINT_INDEX[n] for n in ("left_foot", "right_foot", "left_ankle", "right_ankle")]] = True
    g, mu = 9.81, 0.8
    metric, Fc, _ = root_wrench(x, x, v, m, feet, g, mu)
    assert metric < 1e-6 * m.sum() * g and abs(Fc[1] - m.sum() * g) < 1e-6  # the ground carries the weight
    air = x + np.array([0.0, 1.0, 0.0])
    none = np.zeros(NUM_JOINTS, dtype=bool)
    metric, _, _ = root_wrench(air, air, v, m, none, g, mu)
    assert abs(metric - m.sum() * g) < 1e-6
    full, before, after, _ = soft_correction(air, air, v, m, none, g, mu, weight=1e6, skip_below=0.0)
    assert abs(before - m.sum() * g) < 1e-6 and after < 1e-3 * before
    com_drop = float((m[:, None] * (air - full)).sum(0)[1] / m.sum())
    assert abs(com_drop - g * H**2) < 1e-6  # it falls by g h^2 in the frame, as free fall would
    part, _, after_part, _ = soft_correction(air, air, v, m, none, g, mu, weight=1e-8, skip_below=0.0)
    assert after < after_part < before and 0 < float(np.abs(part - air).max()) < float(np.abs(full - air).max())
    same, before, after, _ = soft_correction(air, air, v, m, none, g, mu, weight=1e6, skip_below=2 * m.sum() * g)
    assert np.array_equal(same, air) and before == after
    # a sideways acceleration beyond friction (12 m/s^2 > mu g): at least the distance of the
    # needed force (12, g) M from the cone |f_x| <= mu f_y is left over
    slide = x + np.array([12.0, 0.0, 0.0]) * H**2
    metric, _, _ = root_wrench(slide, x, v, m, feet, g, mu)
    assert metric > 0.99 * m.sum() * (12.0 - mu * g) / np.sqrt(1 + mu**2)
    # corrected gently (max_move), the feet on the ground stay where static friction holds them
    fixed, before, after, _ = soft_correction(slide, x, v, m, feet, g, mu, weight=1e6, skip_below=0.0, max_move=0.001)
    moved = np.linalg.norm(fixed - slide, axis=1)
    assert moved.max() <= 0.001 + 1e-12 and moved[feet].max() == 0 and after < before
    # with the frame before's contact forces as the guess, the NNLS answer is the same
    metric2, _, p = root_wrench(slide, x, v, m, feet, g, mu)
    again, _, _ = root_wrench(slide, x, v, m, feet, g, mu, guess=p["c"])
    assert abs(again - metric2) < 1e-6 * m.sum() * g


def test_range_of_motion_is_the_datas_own(tmp_path):
    """A knee-like joint that only bends about x between 0 and 2 rad: a pose inside stays, one bent
    past the data or turned about another axis comes back to the boundary; the file round-trips
    and a corrupt one is named."""
    from avatar_motor.physics import limits
    g = torch.Generator().manual_seed(0)

    def hinge(angles):
        aa = torch.zeros(len(angles), 21, 3, dtype=torch.float64)
        aa[..., 0] = angles[:, None]
        return rot.axis_angle_to_matrix(aa)

    train = hinge(torch.rand(4000, generator=g, dtype=torch.float64) * 2.0)
    held = hinge(torch.rand(1000, generator=g, dtype=torch.float64) * 2.0)
    rom = limits.fit(train, held, anchors=32, generator=g)
    assert bool((rom.radius < 0.1).all())  # 32 anchors over 2 rad: a few hundredths apart
    inside = hinge(torch.tensor([1.0], dtype=torch.float64))
    assert torch.allclose(limits.project(inside, rom), inside)
    past = hinge(torch.tensor([2.6], dtype=torch.float64))
    back = rot.matrix_to_axis_angle(limits.project(past, rom))
    assert bool(((back[..., 0] - 2.0).abs() < 0.15).all()) and bool((back[..., 1:].abs() < 1e-6).all())
    aa = torch.zeros(1, 21, 3, dtype=torch.float64)
    aa[..., 0], aa[..., 1] = 1.0, 0.6  # bent and twisted off the hinge
    off = limits.project(rot.axis_angle_to_matrix(aa), rom)
    d = limits._angles(rot.matrix_to_quat(off), rom.anchors).amin(-1)
    assert bool((d <= rom.radius + 1e-9).all())  # on the boundary of the data's set
    limits.save(rom, tmp_path / "rom.safetensors")
    again = limits.load(tmp_path / "rom.safetensors")
    # shipped in float16: within its precision, and the fingerprint is of those values
    assert torch.allclose(again.radius, rom.radius, atol=1e-3) and torch.allclose(again.anchors, rom.anchors, atol=1e-3)
    assert limits.fingerprint(again) == limits.fingerprint(rom)
    (tmp_path / "bad.safetensors").write_bytes(b"not a file")
    with pytest.raises(ValueError, match="not a readable range-of-motion"):
        limits.load(tmp_path / "bad.safetensors")
    # shipped as models/range-of-motion: found by default_range, with its fingerprint in config.json
    assert limits.default_range(tmp_path / "models") is None
    cfg = limits.LimitsConfig(out=str(tmp_path / "models" / "range-of-motion"))
    limits.ship(rom, cfg, {"joints_inside": 0.99}, "card")
    found = limits.default_range(tmp_path / "models")
    info = json.loads((tmp_path / "models" / "range-of-motion" / "config.json").read_text())
    assert info["fingerprint"] == limits.fingerprint(found) and info["recipe"]["cover"] == cfg.cover
    (tmp_path / "models" / "range-of-motion" / limits.FILE).write_bytes(b"\0" * 100)
    with pytest.raises(ValueError, match="avatar-motor limits --config"):
        limits.default_range(tmp_path / "models")


def test_the_range_of_motion_energy_pulls_a_bent_joint_back():
    """A body whose shin was thrown 1.5 rad past what its data holds: one step with the range of
    motion energy (no prior) brings the shin back toward the range; without it, it stays bent."""
    from avatar_motor.physics import limits
    x0, root, local, off = _standing()
    g = torch.Generator().manual_seed(0)
    wiggle = rot.axis_angle_to_matrix(0.15 * torch.randn(600, 21, 3, generator=g, dtype=torch.float64))
    rom = limits.fit(local @ wiggle, local @ wiggle[:200], anchors=64, generator=g)
    hip, knee, ankle, foot = (JOINT_INDEX[f"left_{n}"] for n in ("hip", "knee", "ankle", "foot"))
    R = rot.axis_angle_to_matrix(torch.tensor([1.5, 0.0, 0.0], dtype=torch.float64))
    x = x0.clone()
    for j in (ankle, foot):
        x[:, j] = x[:, knee] + (R @ (x0[:, j] - x0[:, knee])[..., None])[..., 0]
    x[..., 1] += 0.5  # off the ground, so only the joint limits act on the shin

    def shin_error(cfg, rom_or_none):
        b = prepare(off, cfg)
        y, v = x, torch.zeros_like(x)
        for _ in range(5):  # as physics.segment runs it: each frame the body of its rotations
            _, rr, ll, J = pose_from_particles(y, root, local, off)
            y, v, _ = step(b, J, v, _held(x0, root, local), cfg=cfg, rom=rom_or_none, pose=(rr, ll))
        want = rot.normalize(x0[:, ankle] - x0[:, knee])
        got = rot.normalize(y[:, ankle] - y[:, knee])
        return float(torch.acos((want * got).sum(-1).clamp(-1, 1)))

    free = shin_error(PhysicsConfig(kinematic=0.0, contact=0.0, gravity=0.0), None)
    held = shin_error(PhysicsConfig(kinematic=0.0, contact=0.0, gravity=0.0), rom)
    assert free > 1.3 and held < free - 0.3, (free, held)

def test_the_joint_limits_are_internal_forces(monkeypatch):
    """The step that turns a shin bent past its limit back does not move the body (no net force)
    and spins it less than a range-of-motion pull with its rigid part left in (the rigid part is
    taken out to first order, at the pose the step starts from: a 1.5 rad bend still turns the
    body a little)."""
    from avatar_motor.physics import limits, solver
    x0, root, local, off = _standing()
    g = torch.Generator().manual_seed(0)
    wiggle = rot.axis_angle_to_matrix(0.15 * torch.randn(600, 21, 3, generator=g, dtype=torch.float64))
    rom = limits.fit(local @ wiggle, local @ wiggle[:200], anchors=64, generator=g)
    knee, ankle, foot = (JOINT_INDEX[f"left_{n}"] for n in ("knee", "ankle", "foot"))
    R = rot.axis_angle_to_matrix(torch.tensor([1.5, 0.0, 0.0], dtype=torch.float64))
    x = x0.clone()
    for j in (ankle, foot):
        x[:, j] = x[:, knee] + (R @ (x0[:, j] - x0[:, knee])[..., None])[..., 0]
    cfg = PhysicsConfig(kinematic=0.0, contact=0.0, gravity=0.0)
    b = prepare(off, cfg)
    _, rr, ll, J = pose_from_particles(x, root, local, off)

    def momenta():
        y, v, _ = step(b, J, torch.zeros_like(J), _held(x0, root, local), cfg=cfg, rom=rom, pose=(rr, ll))
        assert float((y - J).norm(dim=-1).max()) > 0.05  # it did turn the shin
        return _momenta(J, v, b.masses)

    p, L = momenta()
    monkeypatch.setattr(solver, "rigid_part", lambda d, x, m: torch.zeros_like(d))
    p_kept, L_kept = momenta()
    assert float(p.norm()) < 1e-9 < 10 < float(p_kept.norm()), (p, p_kept)  # kept, it moves the body at 0.7 m/s
    assert float(L.norm()) < 0.75 * float(L_kept.norm()), (L, L_kept)


def _segment_inputs(N: int = 15, K: int = 1):
    from avatar_motor.body.motion_state import pack
    x0, root, local, off = _standing()
    state = pack(x0[:, 0], root, local, x0, torch.zeros_like(x0))  # (1, 267)
    cands = state[:, None, None].expand(1, K, N, -1).clone()
    return state, cands, off


def test_a_physics_segment_is_one_body_and_stands_when_the_model_stands():
    from avatar_motor.body.motion_state import body_mismatch, joints_of
    from avatar_motor.physics.simulate import segment
    state, cands, off = _segment_inputs()
    frames, balls, chosen, lengths, _ = segment(prepare(off), state, cands)
    assert lengths == [15]  # nothing perturbed it: no reason to resample
    assert frames.shape == (1, 15, 267) and chosen.shape == (1, 15)
    assert float(body_mismatch(frames, off[:, None]).max()) < 1e-6  # joints = FK of the rotations
    assert float((joints_of(frames) - joints_of(state)[:, None]).norm(dim=-1).max()) < 0.02
    v = frames[..., -66:].reshape(1, 15, 22, 3)
    J = joints_of(frames)
    assert torch.allclose(v[:, 1:], (J[:, 1:] - J[:, :-1]) * 30, atol=1e-9)  # velocities are the body's


def test_a_compliant_body_whose_model_hovers_lands_and_stays_down():
    """The model's candidates hold the standing pose 10 cm above the floor. A compliant body in
    that pose falls onto the floor, stays there (the candidates that follow are shifted by the
    fall, so they do not pull it back up) and follows them to the end of the segment; with
    ballistic 0 the prior holds it in the air."""
    from avatar_motor.body.motion_state import joints_of, pack
    from avatar_motor.physics.simulate import segment
    x0, root, local, off = _standing()
    up = x0 + torch.tensor([0.0, 0.10, 0.0], dtype=torch.float64)
    state = pack(up[:, 0], root, local, up, torch.zeros_like(up))
    cands = state[:, None, None].expand(1, 1, 15, -1).clone()

    def lowest(cfg):
        frames, _, _, lengths, _ = segment(prepare(off, cfg), state, cands, cfg)
        return (joints_of(frames)[0, :, :, 1] - REST_HEIGHT).amin(-1), lengths

    low, lengths = lowest(PhysicsConfig())
    assert lengths == [15]
    # down within 4 frames (0.14 s to fall 10 cm); it rebounds by about 2 cm, within the margin
    # it still touches at (FLIGHT_MARGIN), and settles
    assert float(low[3:].abs().max()) < 0.03 and float(low[-5:].abs().max()) < 0.005, low
    held, _ = lowest(PhysicsConfig(ballistic=0.0))
    assert float(held.min()) > 0.07, held


def test_an_undisturbed_compliant_body_on_the_ground_is_held_up_but_not_in_the_air():
    """PhysicsConfig.held_weight: a compliant body standing on its candidates' pose sags under
    gravity against the prior's pull; held, by less (the prior's candidates then start from a
    body nearer them). A body in the air is not held: it falls as an unheld one does."""
    from avatar_motor.body.motion_state import joints_of, pack
    from avatar_motor.physics.simulate import segment
    state, cands, off = _segment_inputs()
    b = prepare(off)
    rest = joints_of(state)[0, :, 1]

    def sag(st, cs, holding):
        frames, *_ = segment(b, st, cs, holding=holding)
        return joints_of(frames)[0, -1, :, 1] - joints_of(st)[0, :, 1]

    free, held = sag(state, cands, None), sag(state, cands, torch.tensor([True]))
    hips = rest > 0.5  # above the knees: what the legs carry
    assert float(free[hips].mean()) < -1e-3  # unheld, the body sinks
    assert float(held[hips].mean()) > 0.5 * float(free[hips].mean())  # held, by less than half of that
    assert torch.equal(sag(state, cands, torch.tensor([False])), free)
    x0, root, local, _ = _standing()
    up = x0 + torch.tensor([0.0, 0.3, 0.0], dtype=torch.float64)  # in the air: nothing holds it
    flying = pack(up[:, 0], root, local, up, torch.zeros_like(up))
    fly_cands = flying[:, None, None].expand(1, 1, 3, -1).clone()
    frames_free, *_ = segment(b, flying, fly_cands)
    frames_held, *_ = segment(b, flying, fly_cands, holding=torch.tensor([True]))
    assert torch.equal(joints_of(frames_free)[:, 0], joints_of(frames_held)[:, 0])


def test_the_prior_s_pull_carries_over_a_join_and_decays():
    """A body held off its candidates feels their pull; the next segment's candidates start at the
    body, so without the pull carried over it would drop to nothing at the join (a jerk). (Its decay
    over the segment: the crowd's test of the join's jerk, eval realism --physics.)"""
    from avatar_motor.body.motion_state import joints_of
    from avatar_motor.physics.simulate import segment
    state, cands, off = _segment_inputs()
    # the feet held by static friction, so that only the carried pull can move them (with Coulomb's
    # the body it pulls drags a lightly loaded foot along: the friction test's business)
    b = prepare(off, PhysicsConfig(friction=1e9))
    ahead = cands.clone()
    ahead[..., -132:-66] += torch.tensor([0.0, 0.0, 0.1], dtype=torch.float64).repeat(22)  # 10 cm ahead of the body
    _, _, _, _, pulls = segment(b, state, ahead)
    last = pulls[:, 0]
    assert float(last[..., 2].mean()) > 0.01  # the body lags behind its candidates: pulled forward
    # a segment from there with candidates where the body is: the pull continues, then fades
    _, _, _, _, plain = segment(b, state, cands)
    _, _, _, _, carried = segment(b, state, cands, pull=last)
    up = joints_of(state)[0, :, 1] > 0.3  # the feet stay planted: their pull is not carried (skating)
    big = float(last[:, up].norm(dim=-1).max())
    assert float(plain[:, 0, up].norm(dim=-1).max()) < 0.2 * big  # (what holds it up against gravity)
    # the same way, a share of it (the body already moves toward it in that first frame, as it did
    # in the frame `last` was taken at)
    assert float(carried[:, 0, up, 2].min()) > 0.3 * float(last[:, up, 2].max())
    feet = [JOINT_INDEX["left_foot"], JOINT_INDEX["right_foot"]]  # (the ankles follow the shins a little)
    assert float((carried[:, 0, feet] - plain[:, 0, feet]).norm(dim=-1).max()) < 0.1 * big


def test_a_body_turned_calm_keeps_the_pull_s_strength_not_its_distance():
    """The pull is carried as weight x distance: a body that turns stiff at a join (calm, its
    kinematic weight 10x) is pulled as hard as before, so it moves less toward where the compliant
    body was pulled; carried as a distance, the stiff body would jump to it."""
    from avatar_motor.physics.simulate import segment
    state, cands, off = _segment_inputs()
    cfg = PhysicsConfig()
    ahead = cands.clone()
    ahead[..., -132:-66] += torch.tensor([0.0, 0.0, 0.1], dtype=torch.float64).repeat(22)
    _, _, _, _, pulls = segment(prepare(off, cfg), state, ahead, cfg)
    last = pulls[:, 0]
    moved = {}
    for calm in (False, True):
        b = prepare(off, cfg, torch.tensor([calm]))
        assert float(b.kinematic[0]) == (cfg.kinematic_calm if calm else cfg.kinematic)
        plain, *_ = segment(b, state, cands, cfg)
        carried, *_ = segment(b, state, cands, cfg, pull=last)
        moved[calm] = float((carried[0, 0, 135:201] - plain[0, 0, 135:201]).abs().max())
    assert 0 < moved[True] < 0.5 * moved[False]


def test_a_calm_body_s_toes_roll_down_to_the_ground_a_compliant_one_s_grip_at_rest_height():
    """CALM_CONTACT_HEIGHT: a toe 1 cm above the floor (below FOOT_CLEARANCE, as a foot rolling over
    its toes puts it) is left where the model put it on a calm body; a compliant body's is held at
    its resting height where it was the frame before (static friction)."""
    from avatar_motor.physics.solver import CALM_CONTACT_HEIGHT
    x, _, _, off = _standing(2)
    f = JOINT_INDEX["left_foot"]
    rolled = x.clone()
    rolled[:, f] += torch.tensor([0.03, 0.0, 0.02], dtype=torch.float64)
    rolled[:, f, 1] = 0.01
    b = prepare(off, PhysicsConfig(), torch.tensor([False, True]))
    assert torch.equal(b.contact_height[0], REST_HEIGHT) and torch.equal(b.contact_height[1], CALM_CONTACT_HEIGHT)
    p = project_ground(rolled, x, height=b.contact_height)
    assert torch.allclose(p[0, f], torch.tensor([x[0, f, 0], REST_HEIGHT[f], x[0, f, 2]], dtype=torch.float64))
    assert torch.equal(p[1], rolled[1])
    sunk = rolled.clone()
    sunk[:, f, 1] = -0.01  # below the floor itself: held on a calm body too
    assert float(project_ground(sunk, x, height=b.contact_height)[1, f, 1]) == 0.0


def test_a_ball_knocks_the_body_and_bounces_off():
    """3 kg at 10 m/s into the chest from the front: the chest goes back, the ball comes back slower,
    and the momentum the ball lost is about what the body took (restitution below 1)."""
    from avatar_motor.body.motion_state import joints_of
    from avatar_motor.physics.simulate import Ball, segment
    state, cands, off = _segment_inputs()
    b = prepare(off)
    chest = joints_of(state)[0, JOINT_INDEX["spine3"]]
    ball = Ball(chest + torch.tensor([0.0, 0.0, 0.6], dtype=torch.float64), torch.tensor([0.0, 0.0, -10.0], dtype=torch.float64),
                3.0, 0.11)
    frames, balls, _, lengths, _ = segment(b, state, cands, balls=[[ball]])
    J = joints_of(frames)
    after = balls[0][-1][0]
    assert float(after.velocity[2]) > 0  # bounced back toward +z
    assert float(J[0, :8, JOINT_INDEX["spine3"], 2].min()) < float(chest[2]) - 0.03  # the chest was knocked back
    free, _, _, _, _ = segment(b, state, cands)  # no ball: the chest stays
    assert float((joints_of(free)[0, :, JOINT_INDEX["spine3"]] - chest).norm(dim=-1).max()) < 0.01
    hit_frame = next(i for i, bs in enumerate(balls[0]) if float(bs[0].velocity[2]) > 0)
    assert hit_frame <= 3  # 0.6 m at 10 m/s: within two frames
    assert lengths == [hit_frame + 1]  # the segment ends at the hit, to be sampled again from there


def test_a_spring_pulls_the_hand():
    from avatar_motor.body.motion_state import joints_of
    from avatar_motor.physics.simulate import Spring, segment
    state, cands, off = _segment_inputs()
    w = JOINT_INDEX["right_wrist"]
    hand = joints_of(state)[0, w]
    target = hand + torch.tensor([-0.4, 0.3, 0.5], dtype=torch.float64)
    frames, _, _, _, _ = segment(prepare(off), state, cands, springs=[[Spring(w, target, stiffness=800.0)]])
    d0 = float((hand - target).norm())
    d1 = float((joints_of(frames)[0, -1, w] - target).norm())
    assert d1 < 0.7 * d0, (d0, d1)


def test_physics_mode_in_the_crowd(tmp_path):
    """An avatar in physics mode is stepped by the solver with K model candidates per segment; a
    ball thrown at it hits (its segment is cut at the hit and resampled), the frames are one body,
    the same seed gives the same frames, and toggling physics off continues from the frame shown."""
    from avatar_motor.body.motion_state import body_mismatch, joints_of
    from avatar_motor.runtime.crowd import Crowd, RuntimeConfig
    from .conftest_models import tiny_motor
    motor = tiny_motor(tmp_path)

    def run(seed):
        crowd = Crowd(motor, RuntimeConfig(), seed)
        i = crowd.spawn()
        crowd.set_physics(i, True)
        frames = [crowd.next_frames()[i] for _ in range(5)]
        chest = joints_of(crowd.state(i))[JOINT_INDEX["spine3"]].double()
        # from 1 m: it reaches the chest within a few frames (this untrained model's body sags)
        crowd.throw(i, (chest + torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)).tolist(), [0.0, 0.0, -12.0], mass=3.0)
        seen = []
        for _ in range(20):
            frames.append(crowd.next_frames()[i])
            seen.append([b.velocity[2].item() for b in crowd.balls(i)])
        return crowd, i, torch.stack(frames), seen

    crowd, i, frames, seen = run(0)
    assert seen[0] and seen[0][0] < 0 and any(v and v[0] > -11 for v in seen)  # the ball came; the body slowed it
    from avatar_motor.body.skeleton import rest_offsets
    assert float(body_mismatch(frames.double(), rest_offsets(None, torch.float64)).max()) < 1e-4
    _, _, again, _ = run(0)
    assert torch.equal(frames, again)
    crowd.next_frames()
    crowd.set_physics(i, False)  # off: the queue is cut and the model continues from the frame shown
    a = crowd.avatars[i]
    assert a.queue == [] and a.ball_queue == [] and a.balls == [] and crowd.balls(i) == []
    crowd.next_frames()
    assert a.queue and all(not b for b in a.ball_queue)
    with pytest.raises(ValueError, match="not in physics mode"):
        crowd.throw(i, [0, 1, 1], [0, 0, -5])


def test_the_energies_are_the_terms_the_step_minimises_and_the_ground_holds_hard():
    """solver.energies after a step: each term in joules, zero where its constraint holds (no
    momentum energy for a body in free fall with no other energy, no contact energy in the air),
    positive where it acts. A joint the energies leave under the ground ends the step on it."""
    x, root, local, off = _standing()
    cfg = PhysicsConfig(contact=0.0, range_of_motion=0.0, kinematic=0.0)
    b = prepare(off, cfg)
    trace = []
    step(b, x + torch.tensor([0.0, 5.0, 0.0], dtype=torch.float64), torch.zeros_like(x), _held(x, root, local),
         cfg=cfg, trace=trace)
    (e,) = trace
    assert set(e) == {"momentum", "rigidity", "contact", "kinematic"}
    assert all(float(v.abs().max()) < 1e-8 for v in e.values())  # free fall: every term holds (J)
    # the prior wants the body 10 cm lower: its energy, and the ground's, act and are positive
    cfg = PhysicsConfig(range_of_motion=0.0)
    b = prepare(off, cfg)
    trace = []
    low = x - torch.tensor([0.0, 0.10, 0.0], dtype=torch.float64)
    solved, _, _ = step(b, x, torch.zeros_like(x), _held(low, root, local), cfg=cfg, trace=trace)
    assert float(trace[0]["kinematic"]) > 0 and float(trace[0]["momentum"]) > 0
    # the feet were pulled under the ground by the prior: the last projection put them on it
    assert float((solved[..., 1] - REST_HEIGHT).min()) > -1e-9


def test_eval_physics_measures_falls_responses_penetration_and_ghost_forces():
    """eval physics' figures on hand-made motion: a body that drops to the floor and one that
    stands; the one that got up again; a sunk joint; a push's response beyond the unpushed body;
    the root-wrench metric of free fall (none: gravity explains it) and of a body hovering still
    (one body weight: no contact holds it)."""
    from avatar_motor.body.motion_state import STATE_DIM, SLICES
    from avatar_motor.eval.physics import measure, root_wrench_series
    u = unpack(standing_state()[None].double())
    T = 60
    J = u.joints[0].expand(T, 22, 3).clone()  # standing still
    fall = J.clone()
    fall[30:50, :, 1] -= torch.linspace(0, 0.8, 20, dtype=torch.float64)[:, None]  # drops, pelvis to ~0.15 m
    fall[50:, :, 1] -= 0.8
    fall[..., 1] = fall[..., 1].clamp(min=0.02)  # lying on the floor, not in it
    up_again = fall.clone()
    up_again[45:, :, 1] = J[45:, :, 1]
    pushed = J.clone()
    pushed[10:, :, 2] += torch.linspace(0, 0.5, T - 10, dtype=torch.float64)[:, None]  # 0.25 m in the second after
    sunk = J.clone()
    sunk[40, 10, 1] = -0.05  # a foot 5 cm under the ground
    X = torch.zeros(5, T, STATE_DIM, dtype=torch.float64)
    for b, Jb in enumerate((J, fall, up_again, pushed, sunk)):
        X[b, :, SLICES["joints"]] = Jb.reshape(T, 66)
    X[..., SLICES["local_rot"]] = standing_state()[SLICES["local_rot"]].double()
    base = X[[0, 0, 0, 0, 0]]
    row = measure(X.float(), [10] * 5, base.float(), PhysicsConfig(mass=70.0), None)
    assert abs(row["stayed_up"] - 3 / 5) < 1e-6 and abs(row["fell_and_got_up"] - 1 / 5) < 1e-6
    assert abs(row["fell_stayed_down"] - 1 / 5) < 1e-6
    assert abs(row["penetration_cm"] - 5.0) < 0.01
    pushed_only = measure(X[3:4].float(), [10], base[:1].float(), PhysicsConfig(mass=70.0), None)
    assert abs(pushed_only["response_m"] - 0.5 * 30 / 49) < 0.01
    # the root-wrench metric: free fall needs no ground; hovering still needs one body weight
    g = 9.81
    t = torch.arange(10, dtype=torch.float64) / 30
    air = u.joints[0] + torch.tensor([0.0, 3.0, 0.0], dtype=torch.float64)
    falling = air[None] - (0.5 * g * t**2)[:, None, None] * torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    assert float(np.abs(root_wrench_series(falling, PhysicsConfig(mass=70.0, gravity=g))).max()) < 1e-6
    hover = air[None].expand(10, 22, 3)
    assert np.allclose(root_wrench_series(hover, PhysicsConfig(mass=70.0, gravity=g)), 1.0, rtol=1e-6)  # body weights


def test_the_soft_correction_runs_after_an_external_effect_only(tmp_path, monkeypatch):
    """Crowd.SETTLE: a body in physics mode is corrected (DROP §6) and compliant (the kinematic
    weight, not kinematic_calm) from an external effect (a force, a push, a ball, a spring) until
    SETTLE s after it; unperturbed, and just turned on, it is calm."""
    from avatar_motor.runtime import crowd as crowd_module
    from avatar_motor.runtime.crowd import Crowd, RuntimeConfig
    from .conftest_models import tiny_motor
    monkeypatch.setattr(crowd_module, "SETTLE", 0.5)  # shorter than shipped (2 s), for speed
    SETTLE = crowd_module.SETTLE
    crowd = Crowd(tiny_motor(tmp_path), RuntimeConfig(), 0)
    i = crowd.spawn()
    crowd.set_physics(i, True)

    def disturbed():
        job = crowd.prepare(10**9)
        crowd.abandon(job)
        assert job.physics[0].calm != job.physics[0].disturbed  # (the flat floor, nothing near)
        return job.physics[0].disturbed

    assert not disturbed()  # just turned on: nothing hit it
    crowd.step_segment()
    assert not disturbed()
    for act in (lambda: crowd.apply_force(i, "pelvis", [100.0, 0.0, 0.0], 0.1),
                lambda: crowd.push(i, "pelvis", [1.0, 0.0, 0.0]),
                lambda: crowd.throw(i, [0.0, 1.0, 2.0], [0.0, 0.0, -5.0]),
                lambda: crowd.set_spring(i, "left_wrist", [0.3, 1.2, 0.3])):
        act()
        assert disturbed()
        crowd.set_spring(i, "left_wrist", None)
        crowd.avatars[i].pending_velocity = None
        while crowd.avatars[i].frame < crowd.avatars[i].disturbed_until + 1:
            crowd.step_segment()
        assert not disturbed()


def test_a_calm_body_samples_its_own_candidates_and_a_hit_or_an_obstacle_ends_the_calm(tmp_path):
    """A calm body (nothing acting on it, the flat floor, no obstacle within OBSTACLE_CLEARANCE) samples
    candidates_calm segments and is solved with kinematic_calm; a push, a tilted ground or a box
    near it bring back DROP's K candidates and compliant weight."""
    from avatar_motor.physics.environment import Box
    from avatar_motor.physics.environment import OBSTACLE_CLEARANCE
    from avatar_motor.runtime.crowd import Crowd, RuntimeConfig
    from .conftest_models import tiny_motor
    crowd = Crowd(tiny_motor(tmp_path), RuntimeConfig(), 0)
    i, j = crowd.spawn(), crowd.spawn(position=(6.0, 0.0))
    crowd.set_physics(i, True)
    crowd.set_physics(j, True)
    cfg = crowd.cfg.physics

    def calm():
        job = crowd.prepare(10**9)
        crowd.abandon(job)
        phys = list(range(len(job)))
        return [jb.calm for jb in job.physics], crowd._candidate_counts(job, phys)

    assert calm() == ([True, True], [cfg.candidates_calm] * 2)
    frames = crowd.step_segment()  # one calm segment runs (its candidates repeated to the batch's K)
    assert all(torch.isfinite(f).all() for f in frames.values())
    crowd.push(i, "pelvis", [1.5, 0.0, 0.0])
    assert calm() == ([False, True], [cfg.candidates, cfg.candidates_calm])
    crowd.step_segment()  # a compliant body beside a calm one, in one batch
    crowd.avatars[i].disturbed_until = 0
    assert calm()[0] == [True, True]
    pelvis = crowd.state(j)[135:138]
    crowd.add_obstacle((float(pelvis[0]) + OBSTACLE_CLEARANCE, float(pelvis[2])), (0.5, 0.3, 0.5))
    assert calm()[0] == [True, False]  # j is within reach of the box, i 6 m away is not
    crowd.remove_obstacle(0)
    crowd.set_ground((5.0, 0.0))
    assert calm()[0] == [False, False]


def test_a_calm_body_s_candidates_are_joined_to_the_frames_shown_before_a_hit_one_s_are_not(tmp_path):
    """The candidates a calm body follows stiffly go through the join's stages with the frames shown
    before them, as a plain avatar's segment does; a compliant body's continuity is the solver's."""
    from avatar_motor.runtime.crowd import Crowd, RuntimeConfig
    from .conftest_models import tiny_motor
    crowd = Crowd(tiny_motor(tmp_path), RuntimeConfig(), 0)
    i, j = crowd.spawn(), crowd.spawn(position=(3.0, 0.0))
    for a in (i, j):
        crowd.set_physics(a, True)
    from avatar_motor.runtime.crowd import PAST
    for _ in range(30):  # until both have frames shown before them (the tiny model's segments can be short)
        if all(len(a.past) + 1 + len(a.queue) > PAST for a in crowd.avatars.values()):
            break
        crowd.step_segment()
    crowd.push(j, "pelvis", [1.5, 0.0, 0.0])
    seen = []
    stages = crowd._stages

    def spy(ctx, seg):
        seen.append(ctx)
        return stages(ctx, seg)

    crowd._stages = spy
    crowd.step_segment()
    phys = [c for c in seen if c.past is not None and len(c.x0) == 1 + crowd.cfg.physics.candidates]
    assert len(phys) == 1, [len(c.x0) for c in seen]  # one call for both bodies' candidates
    has = phys[0].has_past.tolist()
    assert has == [True] + [False] * crowd.cfg.physics.candidates  # i calm (1 candidate), j hit (K)


def test_the_crowd_carries_the_pull_from_segment_to_segment(tmp_path):
    from avatar_motor.runtime.crowd import Crowd, RuntimeConfig
    from .conftest_models import tiny_motor
    crowd = Crowd(tiny_motor(tmp_path), RuntimeConfig(), 0)
    i = crowd.spawn()
    crowd.set_physics(i, True)
    assert crowd.prepare(1).physics[0].pull is None  # spawned: nothing pulled it yet
    for _ in range(20):
        crowd.next_frames()
    a = crowd.avatars[i]
    assert len(a.pull_queue) == len(a.queue) and all(p.shape == (22, 3) for p in a.pull_queue)
    assert a.shown_pull is not None and a.shown_pull.shape == (22, 3)
    job = crowd.prepare(10**6).physics[0]  # (every avatar, whatever it has queued)
    # the pull at the frame the next segment continues: the last queued, or the one shown
    assert torch.equal(job.pull, a.pull_queue[-1] if a.queue else a.shown_pull)
    crowd.reset(i)
    assert crowd.prepare(10**6).physics[0].pull is None


def test_the_flight_rule_holds_on_a_flat_floor_away_from_obstacles_only():
    """Near an obstacle or on a slope the model keeps its hold of a body in the air (stepping over
    a bar, the rule dropped a foot into it)."""
    from avatar_motor.physics.environment import Box, Environment, Ground
    from avatar_motor.physics.solver import in_flight
    x0, _, _, off = _standing()
    up = x0 + torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    cfg = PhysicsConfig()
    b = prepare(off, cfg)
    px, pz = float(up[0, 0, 0]), float(up[0, 0, 2])
    assert in_flight(b, up, Environment(), cfg).tolist() == [1.0]
    assert in_flight(b, up, Environment(boxes=(Box((px + 5.0, pz), (1.0, 0.2, 0.2)),)), cfg).tolist() == [1.0]
    assert in_flight(b, up, Environment(boxes=(Box((px + 1.0, pz), (1.0, 0.2, 0.2)),)), cfg) is None
    assert in_flight(b, up, Environment(ground=Ground(tilt=(10.0, 0.0))), cfg) is None


def test_a_simulated_avatar_beside_one_drawing_several_candidates(tmp_path):
    """One batch: an avatar in physics mode and a plain one that draws goal_candidates segments
    (as a steered, reaching or walled-in avatar does). The simulated body gets its own candidates,
    not the plain one's extra draws: its frames are those it makes alone in the same crowd (before,
    the first of them was taken from the plain avatar's rows and the batch failed)."""
    from avatar_motor.runtime.crowd import Crowd, RuntimeConfig
    from .conftest_models import tiny_motor
    motor = tiny_motor(tmp_path)

    def run(with_other):
        crowd = Crowd(motor, RuntimeConfig(goal_candidates=4), 0)
        i = crowd.spawn()
        crowd.set_physics(i, True)
        if with_other:
            j = crowd.spawn(position=(3.0, 0.0))
            crowd.set_goal(j, [0.0, 1.0])
        return torch.stack([crowd.next_frames()[i] for _ in range(30)])

    together, alone = run(True), run(False)
    # (the network's batched arithmetic differs in the last bits with the batch's size)
    assert (together - alone).abs().max() < 1e-3, float((together - alone).abs().max())
