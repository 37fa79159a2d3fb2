"""Physics mode's environment (DROP §8.2): a tilted ground, obstacles, and the centre-of-mass
velocity energy (Eq. 16): each projection, the rank-one solve against a dense one, the energy's
exact pull on a free body, and the world's commands in the crowd and the protocol."""
import math

import pytest
import torch

from avatar_motor.body.motion_state import SLICES, unpack
from avatar_motor.body.skeleton import JOINT_INDEX, NUM_JOINTS, rest_offsets
from avatar_motor.physics.environment import (Box, Environment, Ground, aim_round, footprints, lift_above, project_box,
                                              push_out_of_boxes, route, slide_out_of_boxes, touching)
from avatar_motor.physics.solver import (BONES, COLLISION_RADIUS, H, REST_HEIGHT, Candidates, PhysicsConfig, com_pull,
                                         energies, prepare, project_bones, project_ground, solve_global, step)
from avatar_motor.runtime.crowd import standing_state

F = JOINT_INDEX["left_foot"]


def _standing(B: int = 1):
    u = unpack(standing_state().to(torch.float64)[None].expand(B, -1))
    return u.joints.clone(), u.root_rot, u.local_rot, rest_offsets(None, torch.float64).expand(B, NUM_JOINTS, 3)


def test_environment_values_are_checked_with_the_range_in_the_message():
    for make, word in ((lambda: Ground((40.0, 0.0)), "tilt"), (lambda: Ground((0.0, float("nan"))), "tilt"),
                       (lambda: Ground((0.0, 0.0), (1.0,)), "pivot"), (lambda: Box((0.0, 0.0), (1.0, 0.0, 1.0)), "size"),
                       (lambda: Box((0.0, 0.0), (1.0, 1.0, 5.0)), "size"), (lambda: Box(("a", 0.0), (1.0, 1.0, 1.0)), "centre"),
                       (lambda: Environment(boxes=(Box((0.0, 0.0), (1.0, 1.0, 1.0)),) * 33), "obstacles")):
        with pytest.raises(ValueError, match=word):
            make()


def test_a_tilted_ground_is_a_plane_through_its_pivot():
    g = Ground((10.0, -5.0), (1.0, 2.0))
    n = g.normal()
    assert abs(float(n.norm()) - 1.0) < 1e-12 and float(n[1]) > 0.98
    xz = torch.tensor([[3.0, -1.0], [1.0, 2.0]], dtype=torch.float64)
    y = g.height_below(xz)
    p = torch.stack((xz[:, 0], y, xz[:, 1]), -1)
    assert torch.allclose(g.height(p), torch.zeros(2, dtype=torch.float64), atol=1e-12)  # on the plane
    assert float(y[1]) == 0.0  # the pivot stays on the floor
    flat = Ground()
    assert flat.flat and torch.equal(flat.normal(), torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))


def test_ground_projection_on_a_tilted_plane_moves_along_its_normal_from_where_the_joint_was():
    x, _, _, _ = _standing()
    g = Ground((15.0, 0.0))
    env = Environment(g)
    prev = x.clone()
    sunk = x.clone()
    sunk[0, F] += torch.tensor([0.05, -0.3, 0.04], dtype=torch.float64)
    p = project_ground(sunk, prev, env)
    # onto its resting height above the plane, at the frame before's place along the plane
    assert abs(float(g.height(p[0, F])) - float(REST_HEIGHT[F])) < 1e-12
    along = (p[0, F] - prev[0, F]) - ((p[0, F] - prev[0, F]) @ g.normal()) * g.normal()
    assert float(along.norm()) < 1e-12
    high = g.height(sunk[0]) >= REST_HEIGHT
    assert torch.equal(p[0, high], sunk[0, high])  # above the ground: no energy
    # flat, it is the floor at y = 0 as before
    q = project_ground(sunk, prev)
    assert torch.allclose(q[0, F], torch.tensor([prev[0, F, 0], REST_HEIGHT[F], prev[0, F, 2]], dtype=torch.float64))
    # lifting a frame: no joint centre below the plane, moved along its normal
    J = x.clone() - torch.tensor([0.0, 0.2, 0.0], dtype=torch.float64)
    up = lift_above(J, g)
    assert float(g.height(J + up[:, None]).min()) > -1e-12 and torch.allclose(torch.cross(up[0], g.normal(), dim=0),
                                                                              torch.zeros(3, dtype=torch.float64))


def test_a_box_pushes_a_joint_out_through_the_face_it_came_in_by_and_holds_it_there():
    box = Box((0.0, 1.0), (2.0, 0.3, 0.2), yaw=0.0)
    r = COLLISION_RADIUS
    x = torch.zeros(1, NUM_JOINTS, 3, dtype=torch.float64)
    x[..., 1] = 5.0  # every other joint far above the box
    prev = x.clone()
    # a foot walking into the near side (z < 0.9) at 10 cm high: held at the side, where it touched
    prev[0, F] = torch.tensor([0.2, 0.1, 0.9 - r[F] - 0.01], dtype=torch.float64)
    x[0, F] = torch.tensor([0.25, 0.12, 0.95], dtype=torch.float64)
    p = project_box(x, prev, r, box)
    assert torch.allclose(p[0, F], torch.tensor([0.2, 0.1, 0.9 - float(r[F])], dtype=torch.float64))
    assert torch.equal(p[0, :F], x[0, :F])  # joints outside: themselves
    # coming down onto the top: on it, where it was above
    prev[0, F] = torch.tensor([0.1, 0.3 + r[F] + 0.02, 1.0], dtype=torch.float64)
    x[0, F] = torch.tensor([0.12, 0.28, 1.02], dtype=torch.float64)
    p = project_box(x, prev, r, box)
    assert torch.allclose(p[0, F], torch.tensor([0.1, 0.3 + float(r[F]), 1.0], dtype=torch.float64))
    # a turned box: the same in its own frame
    turned = Box((0.0, 0.0), (2.0, 0.3, 0.2), yaw=90.0)  # its depth now along world X
    prev[0, F] = torch.tensor([-0.2, 0.1, 0.3], dtype=torch.float64)
    x[0, F] = torch.tensor([-0.05, 0.1, 0.3], dtype=torch.float64)
    p = project_box(x, prev, r, turned)
    assert abs(float(p[0, F, 0]) + 0.1 + float(r[F])) < 1e-12 and abs(float(p[0, F, 2]) - 0.3) < 1e-12


def test_a_body_is_moved_out_of_a_box_as_one_piece_through_the_nearest_face():
    box = Box((0.0, 1.0), (2.0, 0.3, 0.2))  # top at 0.3 m, sides at z = 0.9 and 1.1
    env = Environment(boxes=(box,))
    r = COLLISION_RADIUS
    J = torch.zeros(2, NUM_JOINTS, 3, dtype=torch.float64)
    J[..., 1] = 1.0  # every joint well above the box ...
    J[0, F] = torch.tensor([0.1, 0.3 + float(r[F]) - 0.04, 1.0], dtype=torch.float64)  # ... but a foot 4 cm into its top
    J[1, F] = torch.tensor([0.1, 0.15, 0.9 - float(r[F]) + 0.03], dtype=torch.float64)  # ... and one 3 cm into its near side
    shift = push_out_of_boxes(J, r, env)
    assert torch.allclose(shift[0], torch.tensor([0.0, 0.04, 0.0], dtype=torch.float64), atol=1e-12)  # stands on it
    assert torch.allclose(shift[1], torch.tensor([0.0, 0.0, -0.03], dtype=torch.float64), atol=1e-12)  # bumped back
    moved = J + shift[:, None]
    R, c, half = box.frame(J.dtype)
    assert not (((moved - c) @ R).abs() < half + r[:, None] - 1e-9).all(-1).any()  # no sphere inside now
    assert torch.equal(push_out_of_boxes(moved, r, env), torch.zeros(2, 3, dtype=torch.float64))
    assert torch.equal(push_out_of_boxes(J, r, Environment()), torch.zeros(2, 3, dtype=torch.float64))


def _walk(B: int, frames: int, step: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """A standing body (B copies) carried `step` (B, 3) m a frame: segments (B, frames, 22, 3) and the frame before."""
    J = _standing(B)[0]
    seg = J[:, None] + step[:, None, None] * torch.arange(1, frames + 1, dtype=torch.float64)[None, :, None, None]
    return seg, J


def _inside(J: torch.Tensor, box: Box, r: torch.Tensor, tol: float = 1e-9) -> torch.Tensor:
    q, e, _, _ = box.local(J, r)
    return ((e - q.abs()) > tol).all(-1).any(-1)


def test_a_body_the_model_moves_alone_is_stopped_by_a_wall_slides_along_one_at_an_angle_and_never_goes_up():
    """slide_out_of_boxes: walking straight at a wall (5 cm a frame) the body stops at its face and
    stays stopped while its model walks on; at a wall turned 30 degrees it keeps going along the
    face; a body at 30 cm a frame does not pop through a 4 cm wall; the shift is horizontal (a body
    stepping onto a low box is not lifted) and zero for a body no box is near."""
    r = COLLISION_RADIUS
    wall = Box((0.0, 1.0), (3.0, 1.5, 0.1))
    thin = Box((0.0, 1.0), (3.0, 1.5, 0.04))
    step = torch.tensor([[0.0, 0.0, 0.05], [0.0, 0.0, 0.30], [0.0, 0.0, 0.05]], dtype=torch.float64)
    seg, before = _walk(3, 40, step)
    seg[2] += torch.tensor([20.0, 0.0, 0.0], dtype=torch.float64)  # far from every box
    before[2] += torch.tensor([20.0, 0.0, 0.0], dtype=torch.float64)
    for box in (wall, thin):
        shift = slide_out_of_boxes(seg, before, r, Environment(boxes=(box,)))
        moved = seg + shift[:, :, None]
        assert not _inside(moved, box, r).any()
        assert torch.equal(shift[..., 1], torch.zeros_like(shift[..., 1])) and torch.equal(shift[2], torch.zeros_like(shift[2]))
        for b in (0, 1):  # in front of the wall, not behind it: the pelvis stopped short of its near face
            front = float(box.centre[1]) - box.size[2] / 2
            assert float(moved[b, :, 0, 2].max()) < front
            assert float(moved[b, -1, 0, 2]) == pytest.approx(float(moved[b, -10, 0, 2]), abs=1e-9)  # stays stopped
    # at an angle the body keeps the motion along the face
    turned = Box((0.0, 1.0), (3.0, 1.5, 0.1), 30.0)
    seg, before = _walk(1, 60, step[:1])
    shift = slide_out_of_boxes(seg, before, r, Environment(boxes=(turned,)))
    moved = seg + shift[:, :, None]
    assert not _inside(moved, turned, r).any()
    assert float(moved[0, -1, 0, 0]) < -0.5  # it slid sideways along the turned face (toward -x)
    # a box to step on is a wall too: never a lift
    step_box = Box((0.0, 0.5), (3.0, 0.15, 1.0))
    shift = slide_out_of_boxes(seg, before, r, Environment(boxes=(step_box,)))
    assert torch.equal(shift[..., 1], torch.zeros_like(shift[..., 1])) and not _inside(seg + shift[:, :, None], step_box, r).any()
    assert torch.equal(slide_out_of_boxes(seg, before, r, Environment()), torch.zeros(1, 60, 3, dtype=torch.float64))
    # a hand swung through a wall between two frames (never inside at a frame) counts as inside:
    # the body is put back on the side it came from, not left straddling the wall
    H = JOINT_INDEX["left_wrist"]
    J0 = _standing(1)[0]
    ahead = float((J0[0, :, 2] + r).max())  # the body's front (its toes), 2 cm before the 10 cm wall at z = 1
    before = J0 + torch.tensor([0.0, 0.0, 1.0 - 0.05 - 0.02 - ahead], dtype=torch.float64)
    swung = before.clone()
    swung[0, H, 2] = 1.0 + 0.05 + float(r[H]) + 0.01  # the hand 1 cm behind the wall the next frame
    shift = slide_out_of_boxes(swung[:, None], before, r, Environment(boxes=(wall,)))
    assert float(swung[0, H, 2] + shift[0, 0, 2]) == pytest.approx(1.0 - 0.05 - float(r[H]), abs=1e-9)  # at the near face


def test_an_arm_round_a_walls_end_moves_the_body_off_the_end_not_to_and_fro():
    """A body beyond a thin wall's end with its arm wrapped round it (the shoulder came into the
    wall from one side, the elbow from the other, the hand beyond the far face): pushing each
    sphere out by its own face pushes the body to and fro and leaves it in the wall. It leaves along
    the wall, past its end, by the least that frees every sphere, and nothing is taken through."""
    r = COLLISION_RADIUS
    wall = Box((0.0, 0.0), (2.0, 1.5, 0.1))  # x in [-1, 1], z in [-0.05, 0.05]
    S, E, W = (JOINT_INDEX[n] for n in ("right_shoulder", "right_elbow", "right_wrist"))
    J0 = _standing(1)[0]
    before = J0 - J0[:, :1] * torch.tensor([1.0, 0.0, 1.0], dtype=torch.float64) + torch.tensor([1.6, 0.0, 0.0], dtype=torch.float64)
    now = before.clone()
    for j, z_before, z_now in ((S, 0.25, 0.03), (E, -0.25, -0.03), (W, -0.3, -0.25)):
        before[0, j] = torch.tensor([0.85, 1.0, z_before], dtype=torch.float64)
        now[0, j] = torch.tensor([0.85, 1.0, z_now], dtype=torch.float64)
    shift = slide_out_of_boxes(now[:, None], before, r, Environment(boxes=(wall,)))[0, 0]
    moved = now + shift
    assert not _inside(moved[:, None], wall, r).any()
    assert float(shift[2]) == 0.0 and float(shift[0]) == pytest.approx(1.0 + float(r[[S, E, W]].max()) - 0.85, abs=1e-9)


def test_the_shortest_way_round_obstacles_keeps_the_clearance_and_bends_only_at_corners():
    wall = Box((0.0, 2.0), (3.0, 1.5, 0.1))
    env = Environment(boxes=(wall,))
    assert torch.equal(route((0.0, 0.0), (3.0, 0.0), env, 0.5), torch.tensor([[0.0, 0.0], [3.0, 0.0]], dtype=torch.float64))
    assert torch.equal(route((0.0, 0.0), (0.0, 4.0), Environment(), 0.5)[-1], torch.tensor([0.0, 4.0], dtype=torch.float64))
    way = route((0.4, 0.0), (0.4, 4.0), env, 0.5)  # the wall's +x end is the nearer
    assert len(way) == 4 and torch.equal(way[0], torch.tensor([0.4, 0.0], dtype=torch.float64))
    assert torch.allclose(way[1:3], torch.tensor([[2.01, 1.44], [2.01, 2.56]], dtype=torch.float64))
    # every leg keeps the clearance: points along it are outside the grown footprint
    c, A, h = footprints(env, 0.5)
    t = torch.linspace(0, 1, 101, dtype=torch.float64)[:, None]
    for p, q in zip(way[:-1], way[1:]):
        local = (p + t * (q - p) - c[0]) @ A[0]
        assert not bool((local.abs() < h[0] - 1e-6).all(-1).any())
    # a body already against the wall (within the clearance) still finds its way round
    assert len(route((0.4, 1.8), (0.4, 4.0), env, 0.5)) == 4
    # round a turned wall and between two boxes the way is no longer than the best corner path
    two = Environment(boxes=(Box((-1.0, 2.0), (1.6, 1.0, 0.2)), Box((1.0, 2.0), (1.6, 1.0, 0.2))))
    way = route((0.0, 0.0), (0.0, 4.0), two, 0.3)  # through the 40 cm gap? no: it needs 60 cm
    assert len(way) == 4 and float(way[1:3, 0].abs().min()) > 1.8 - 1e-6
    assert len(route((0.0, 0.0), (0.0, 4.0), two, 0.15)) == 2  # with 15 cm clearance the gap is open
    # a goal walled in on every side: straight at it (the walls hold the body)
    ring = Environment(boxes=tuple(Box(cz, sz) for cz, sz in (((0.0, 5.0), (3.0, 1.0, 0.2)), ((0.0, 3.0), (3.0, 1.0, 0.2)),
                                                                ((-1.5, 4.0), (0.2, 1.0, 2.2)), ((1.5, 4.0), (0.2, 1.0, 2.2)))))
    assert len(route((0.0, 0.0), (0.0, 4.0), ring, 0.3)) == 2


def test_a_body_heads_for_a_point_along_its_way_round_an_obstacle():
    """aim_round: the point 3 m along the way round the wall, unless the line to it cuts through
    the footprint grown by half the clearance: then the way's first corner."""
    from avatar_motor.physics.environment import _crossing
    env = Environment(boxes=(Box((0.0, 2.0), (3.0, 1.5, 0.1)),))
    c, A, h = footprints(env, 0.25)
    kinds = set()
    for start in ((0.0, 0.0), (0.0, -3.0), (2.3, 0.5), (-1.0, 1.0)):
        s = torch.tensor(start, dtype=torch.float64)
        aim, direct = aim_round(start, (0.0, 4.0), env, 0.5, 3.0)
        way = route(start, (0.0, 4.0), env, 0.5)
        assert not direct and len(way) > 2
        if torch.allclose(aim, way[1]) and float(way[1].sub(s).norm()) < 3.0 - 1e-6:
            kinds.add("corner")
            legs = (way[1:] - way[:-1]).norm(dim=-1).cumsum(0)
            k = int((legs < 3.0).sum())
            along = way[k] + (3.0 - float(legs[k - 1])) / float(legs[k] - legs[k - 1]) * (way[k + 1] - way[k])
            assert bool(_crossing(s[None], along[None], c, A, h).any())  # the 3 m point was behind the corner
        else:
            kinds.add("along")
            assert not bool(_crossing(s[None], aim[None], c, A, h).any())
            # on the way, 3 m along it
            d = ((way[:-1, None] - aim) .norm(dim=-1) + (way[1:, None] - aim).norm(dim=-1) - (way[1:] - way[:-1]).norm(dim=-1)[:, None])
            k = int(d[:, 0].argmin())
            assert float(d[k]) < 1e-9
            assert float((way[1:k + 1] - way[:k]).norm(dim=-1).sum() + (aim - way[k]).norm()) == pytest.approx(3.0, abs=1e-9)
    assert kinds == {"corner", "along"}
    aim, direct = aim_round((0.0, 0.0), (3.0, 0.0), env, 0.5, 3.0)
    assert direct and torch.equal(aim, torch.tensor([3.0, 0.0], dtype=torch.float64))
    assert aim_round((0.0, 0.0), (0.0, 4.0), env, 0.0, 3.0)[1]  # clearance 0: no routing


def test_a_reaching_avatar_is_aimed_round_a_wall_and_stopped_only_at_its_target(tmp_path):
    """The crowd gives a reaching avatar's segment (its target condition, its facing goal) the
    point aim_round picks when a wall stands between it and its target, and no arrival goal there."""
    from avatar_motor.model.adaptor import AdaptedDenoiser, AdaptorConfig
    from avatar_motor.runtime.crowd import Crowd, RuntimeConfig
    from .conftest_models import tiny_motor
    motor = tiny_motor(tmp_path)
    ad = AdaptedDenoiser(motor.net, AdaptorConfig(control="target")).eval()
    crowd = Crowd(motor, RuntimeConfig(), adaptors=ad)
    i = crowd.spawn(position=(0.0, 0.0))
    a = crowd.avatars[i]
    crowd.set_target(i, (0.0, 4.0))
    assert torch.equal(crowd._aim(a)[0], a.target)  # nothing in the way
    crowd.add_obstacle((0.0, 2.0), (3.0, 1.5, 0.1))
    pelvis = crowd._pelvis_xz(a)
    want, _ = aim_round(pelvis, a.target, crowd.environment, crowd.cfg.route_clearance, crowd.cfg.route_lookahead)
    aim, direct = crowd._aim(a)
    assert not direct and torch.allclose(aim.double(), want, atol=1e-6)
    batch = crowd.prepare(10 ** 6)
    assert torch.allclose(batch.targets[0].double(), want, atol=1e-6)
    assert torch.allclose(batch.facing_goal[0][[0, 2]].double(), (want - pelvis) / (want - pelvis).norm(), atol=1e-5)
    crowd.set_target(i, (float(pelvis[0]), float(pelvis[1]) + 0.3))  # near and in the open: walked onto it
    assert crowd._velocity_goal(a, *crowd._aim(a)) is not None
    assert crowd._velocity_goal(a, want, False) is None  # routed: never an arrival at the aim point


def test_the_magnet_without_a_reaching_adaptor_steers_round_a_wall(tmp_path):
    """The world's own magnet (a velocity goal when no reaching adaptor is served) heads for
    aim_round's point, at full speed, instead of straight into the wall."""
    from avatar_motor.serve.world import World
    from .conftest_models import tiny_motor
    world = World(tiny_motor(tmp_path))
    i = world.apply({"type": "spawn"})["avatar"]
    world.apply({"type": "target", "avatar": i, "position": [0.0, 4.0], "speed": 1.2})
    pelvis = world.crowd.state(i)[[0, 2]].double()
    straight = world.crowd.goal_velocity(i)[[0, 2]].double()
    assert torch.allclose(straight / straight.norm(), (torch.tensor([0.0, 4.0]) - pelvis) / (torch.tensor([0.0, 4.0]) - pelvis).norm(), atol=1e-5)
    world.apply({"type": "obstacle", "centre": [0.0, 2.0], "size": [3.0, 1.5, 0.1]})
    world._steer_to_target(i)
    v = world.crowd.goal_velocity(i)[[0, 2]].double()
    cfg = world.crowd.cfg
    aim, direct = aim_round(pelvis, (0.0, 4.0), world.crowd.environment, cfg.route_clearance, cfg.route_lookahead)
    assert not direct and torch.allclose(v / v.norm(), (aim - pelvis) / (aim - pelvis).norm(), atol=1e-5)
    assert float(v.norm()) == pytest.approx(1.2, rel=1e-5)


def test_an_avatar_not_in_physics_mode_meets_an_obstacle_as_a_wall_and_stays_one_body(tmp_path):
    """In the crowd: an avatar sent at a wall at 1.2 m/s (no physics mode) never puts a joint of the
    body users get (FK of its rotations) into the wall, its velocities stay the backward
    differences of its joints, and its goal is turned along the wall before it (none into it);
    with the shipped model it stops in front of the wall and, with the wall turned, goes past its
    end. (Its goal not routed round the wall: route_ahead 0.)"""
    from avatar_motor.body.motion_state import body_joints, joints_of
    from avatar_motor.runtime.crowd import Crowd, RuntimeConfig
    from .conftest_models import SHIPPED, shipped_or_tiny
    crowd = Crowd(shipped_or_tiny(tmp_path), RuntimeConfig(route_ahead=0.0), 0)
    i = crowd.spawn()
    for _ in range(3):
        crowd.next_frames()
    epoch = crowd.avatars[i].epoch
    crowd.add_obstacle((0.0, 1.8), (3.0, 1.5, 0.1))
    wall = crowd.environment.boxes[0]
    crowd.set_goal(i, [0.0, 1.2])
    a = crowd.avatars[i]
    shown = [crowd.state(i)]
    for _ in range(150):
        shown.append(crowd.next_frames()[i])
        if _inside(joints_of(a.state.double())[None], wall, COLLISION_RADIUS)[0]:
            break
    X = torch.stack(shown).double()
    J = body_joints(X, rest_offsets(crowd.shape(i), torch.float64))
    assert not _inside(J, wall, COLLISION_RADIUS, 1e-4).any()  # float32 states: within 0.1 mm
    v = X[1:, 201:267].reshape(-1, 22, 3)
    assert torch.allclose(v, (J[1:] - J[:-1]) * 30, atol=2e-2)
    # the goal before the wall has no part into it
    near = crowd._along_walls(a, torch.tensor([0.0, 0.0, 1.2]))
    if float(joints_of(a.state.double())[0, 2]) > 1.8 - 0.05 - 0.6:  # within reach of the wall in 0.4 s
        assert float(near[2]) == pytest.approx(0.0, abs=1e-6)
    if SHIPPED.joinpath("model.safetensors").exists():
        assert float(J[-1, 0, 2]) > 1.0  # it walked up to the wall
        crowd.remove_obstacle()
        crowd.reset(i)
        crowd.add_obstacle((0.0, float(J[-1, 0, 2]) + 0.5), (3.0, 1.5, 0.1), 30.0)
        crowd.set_goal(i, [0.0, 1.2])
        for _ in range(240):
            crowd.next_frames()
        assert float(joints_of(crowd.state(i).double())[0, 2]) > float(J[-1, 0, 2]) + 1.0  # round its end
    assert epoch <= crowd.avatars[i].epoch


def test_the_way_ahead_of_a_walk_ends_past_the_obstacle_in_it():
    """way_ahead: None when the line is open (or passes the footprint grown by the margin); else
    the first point of the line at least `ahead` on that is clear of the footprint grown by the
    clearance; None when the line stays in a box for as far as it looks (walled in)."""
    env = Environment(boxes=(Box((0.0, 2.0), (3.0, 1.5, 0.1)),))
    from avatar_motor.physics.environment import way_ahead
    assert way_ahead((0.0, 0.0), (1.0, 0.0), env, 0.5, 3.0, 0.25) is None  # along the wall: open
    assert way_ahead((0.0, 0.0), (0.0, 1.0), env, 0.5, 1.0, 0.25) is None  # the wall beyond the look ahead
    assert way_ahead((0.0, 0.0), (0.0, 0.0), env, 0.5, 3.0, 0.25) is None  # no direction
    p = way_ahead((0.0, 0.0), (0.0, 2.0), env, 0.5, 3.0, 0.25)
    assert p is not None and torch.allclose(p, torch.tensor([0.0, 3.0], dtype=torch.float64))
    p = way_ahead((0.0, 0.0), (0.0, 2.0), env, 0.5, 2.3, 0.25)  # 2.3 m on is within the clearance: further
    assert float(p[1]) == pytest.approx(2.6, abs=1e-6) and float(p[0]) == 0.0
    # a line 1.6 m off the wall's middle passes its end (1.5) within the clearance but outside the margin
    assert way_ahead((1.8, 0.0), (0.0, 1.0), env, 0.5, 3.0, 0.25) is None
    assert way_ahead((1.6, 0.0), (0.0, 1.0), env, 0.5, 3.0, 0.25) is not None
    long = Environment(boxes=(Box((0.0, 2.0), (0.2, 1.5, 3.0)),))  # a wall along the line, longer than it looks
    assert way_ahead((0.0, 0.0), (0.0, 1.0), long, 0.5, 3.0, 0.25, beyond=3.2) is None


def test_a_velocity_goal_into_a_wall_is_aimed_round_it_at_its_speed(tmp_path):
    """An avatar steered at a wall (a stick held forward) is given, for its segment, the way round
    the wall at the stick's speed, facing along it, and the stick's own goal again once the way is
    open; a low bar is not gone round (it is stepped over), nor a goal set with route=False (the
    magnet's, already aimed); route_ahead 0 leaves the goal to stop at the wall."""
    from avatar_motor.runtime.crowd import Crowd, RuntimeConfig
    from .conftest_models import tiny_motor
    crowd = Crowd(tiny_motor(tmp_path), RuntimeConfig(), 0)
    i = crowd.spawn(position=(0.0, 0.0))
    a = crowd.avatars[i]
    crowd.set_goal(i, [0.0, 1.2])
    batch = crowd.prepare(10 ** 6)
    assert torch.equal(batch.v_goal[0], a.v_goal) and torch.equal(batch.facing_goal[0], a.facing_goal)  # the way is open
    crowd.add_obstacle((0.0, 2.0), (3.0, 1.5, 0.1))
    batch = crowd.prepare(10 ** 6)
    v = batch.v_goal[0]
    assert float(v[[0, 2]].norm()) == pytest.approx(1.2, rel=1e-5) and abs(float(v[0])) > 0.5  # sideways, at its speed
    assert torch.allclose(batch.facing_goal[0], v / v.norm(), atol=1e-6)
    pelvis = crowd._pelvis_xz(a).double()
    aim, direct = aim_round(pelvis, (float(pelvis[0]), 3.0), crowd.environment, 0.5, 3.0)
    assert not direct and torch.allclose(v[[0, 2]].double() / 1.2, (aim - pelvis) / (aim - pelvis).norm(), atol=1e-5)
    crowd.set_goal(i, [0.0, 1.2], route=False)
    assert torch.equal(crowd.prepare(10 ** 6).v_goal[0], a.v_goal)
    crowd.set_goal(i, [0.0, 1.2], facing=[1.0, 0.0])  # a facing of its own is kept
    batch = crowd.prepare(10 ** 6)
    assert not torch.equal(batch.v_goal[0], a.v_goal) and torch.equal(batch.facing_goal[0], a.facing_goal)
    crowd.remove_obstacle()
    crowd.add_obstacle((0.0, 2.0), (3.0, 0.2, 0.1))  # a bar: stepped over
    assert torch.equal(crowd.prepare(10 ** 6).v_goal[0], a.v_goal)
    off = Crowd(tiny_motor(tmp_path), RuntimeConfig(route_ahead=0.0), 0)
    j = off.spawn(position=(0.0, 0.0))
    off.set_goal(j, [0.0, 1.2])
    off.add_obstacle((0.0, 2.0), (3.0, 1.5, 0.1))
    assert torch.equal(off.prepare(10 ** 6).v_goal[0], off.avatars[j].v_goal)


def test_a_body_touches_the_ground_or_an_obstacle_within_the_margin_else_it_flies():
    box = Box((0.0, 1.0), (2.0, 0.3, 0.2))  # top at 0.3 m
    r = COLLISION_RADIUS
    J = torch.zeros(4, NUM_JOINTS, 3, dtype=torch.float64)
    J[..., 1] = 1.0  # every joint 1 m up ...
    J[1, F, 1] = float(REST_HEIGHT[F]) + 0.02  # ... but a toe 2 cm above where it rests on the floor
    J[2, F] = torch.tensor([0.1, 0.3 + float(r[F]) + 0.02, 1.0], dtype=torch.float64)  # ... 2 cm above the box
    J[3, F, 1] = float(REST_HEIGHT[F]) + 0.05  # ... 5 cm above the floor: in the air
    env = Environment(boxes=(box,))
    assert touching(J, REST_HEIGHT, r, env, 0.03).tolist() == [False, True, True, False]
    assert touching(J, REST_HEIGHT, r, Environment(), 0.03).tolist() == [False, True, False, False]
    # on a floor tilted 10 degrees about x (0.18 m a metre), that toe touches 1 m uphill, not downhill
    tilted = Environment(Ground(tilt=(10.0, 0.0)))
    both = J[3:].repeat(2, 1, 1)
    both[0, F, 2], both[1, F, 2] = 1.0, -1.0
    assert sorted(touching(both, REST_HEIGHT, r, tilted, 0.03).tolist()) == [False, True]


def test_the_centre_of_mass_energy_is_solved_exactly_with_the_bodys_factor():
    """Sherman-Morrison with the body's factor equals a dense solve of the system with c c^T on
    the horizontal axes, and a body without a goal (weight 0) is solved as before."""
    torch.manual_seed(0)
    x, _, _, off = _standing(3)
    cfg = PhysicsConfig(rigidity=20.0, contact=2.0, range_of_motion=1.5, kinematic=4.0)
    b = prepare(off, cfg)
    y, kin, ground, ranged = (x + 0.05 * torch.randn_like(x) for _ in range(4))
    bones = project_bones(x + 0.02 * torch.randn_like(x), b.rest)
    goal = torch.tensor([[1.0, 0.0, 0.5], [-2.0, 0.0, 0.0], [0.3, 0.0, 0.3]], dtype=torch.float64)
    weight = torch.tensor([1.0, 5.0, 0.0], dtype=torch.float64)
    c, t = com_pull(b.masses, x, goal, weight)
    got = solve_global(b, y, bones, ground, ranged, kin, cfg, (c, t))
    plain = solve_global(b, y, bones, ground, ranged, kin, cfg)
    assert torch.allclose(got[2], plain[2], atol=1e-12)
    m = b.masses[..., None] / H**2
    rhs = m * (y + cfg.contact * ground + cfg.range_of_motion * ranged + cfg.kinematic * kin)
    G = torch.zeros(NUM_JOINTS - 1, NUM_JOINTS, dtype=torch.float64)
    G[torch.arange(NUM_JOINTS - 1), BONES[:, 1]], G[torch.arange(NUM_JOINTS - 1), BONES[:, 0]] = 1.0, -1.0
    for i in range(2):
        for axis in range(3):
            A = b.matrix[i].clone()
            r = rhs[i, :, axis] + G.T @ (cfg.rigidity * torch.minimum(b.masses[i, BONES[:, 0]], b.masses[i, BONES[:, 1]])
                                         / H**2 * bones[i, :, axis])
            if axis != 1:
                A = A + torch.outer(c[i], c[i])
                r = r + c[i] * t[i, axis]
            assert torch.allclose(got[i, :, axis], torch.linalg.solve(A, r), atol=1e-9)
    assert not torch.allclose(got[0], plain[0])


def test_the_centre_of_mass_energy_alone_moves_a_free_body_toward_the_goal_velocity():
    """Momentum and E_com only, rigid bones, no gravity: one step gives the centre of mass the
    velocity w / (1 + w) v_goal (the minimiser of the two quadratics), horizontally only."""
    x, root, local, off = _standing(2)
    cfg = PhysicsConfig(contact=0.0, range_of_motion=0.0, kinematic=0.0, gravity=0.0)
    b = prepare(off, cfg)
    goal = torch.tensor([[1.2, 0.0, -0.6], [0.0, 3.0, 2.0]], dtype=torch.float64)  # a vertical goal is ignored
    w = torch.tensor([1.0, 3.0], dtype=torch.float64)
    cands = Candidates(x[:, None], root[:, None], local[:, None])
    _, v, _ = step(b, x, torch.zeros_like(x), cands, cfg=cfg, goal=(goal, w))
    com_v = (b.masses[..., None] * v).sum(1) / b.masses.sum(-1, keepdim=True)
    want = (w / (1 + w))[:, None] * goal * torch.tensor([1.0, 0.0, 1.0], dtype=torch.float64)
    assert torch.allclose(com_v, want, atol=1e-9)
    trace = []
    step(b, x, torch.zeros_like(x), cands, cfg=cfg, goal=(goal, w), trace=trace)
    assert "com_velocity" in trace[0] and bool((trace[0]["com_velocity"] > 0).all())
    # the energies' term is the one the step minimised: it is smaller at the solution than at rest
    c, t = com_pull(b.masses, x, goal, w)
    rest = energies(b, x, x, x, cands, cfg, com=(c, t))["com_velocity"]
    assert bool((trace[0]["com_velocity"] < rest).all())


def test_the_world_environment_in_the_crowd(tmp_path):
    """set_ground / add_obstacle / remove_obstacle change the world, cut the simulated avatars'
    queues (they met the old world), leave the others alone (none walks into the box), name a bad
    value; a body on a tilted ground stands on it (no joint below the plane)."""
    from avatar_motor.body.motion_state import joints_of
    from avatar_motor.runtime.crowd import Crowd, RuntimeConfig
    from .conftest_models import tiny_motor
    crowd = Crowd(tiny_motor(tmp_path), RuntimeConfig(), 0)
    sim, plain = crowd.spawn(), crowd.spawn(position=(3.0, 0.0))
    crowd.set_physics(sim, True)
    for _ in range(3):
        crowd.next_frames()
    epochs = {i: crowd.avatars[i].epoch for i in (sim, plain)}
    crowd.set_ground((12.0, 0.0), (0.0, 0.0))
    # only the simulated one is cut and resampled
    assert crowd.avatars[sim].epoch > epochs[sim] and crowd.avatars[sim].queue == []
    assert crowd.avatars[plain].epoch == epochs[plain] and crowd.avatars[plain].queue
    k = crowd.add_obstacle((0.0, 1.0), (1.0, 0.2, 0.2), 30.0)
    assert k == 0 and len(crowd.environment.boxes) == 1
    with pytest.raises(ValueError, match="obstacle 3"):
        crowd.remove_obstacle(3)
    with pytest.raises(ValueError, match="tilt"):
        crowd.set_ground((45.0, 0.0))
    assert crowd.environment.ground.tilt == (12.0, 0.0)  # a refused change leaves the world as it was
    g = crowd.environment.ground
    for _ in range(20):
        x = crowd.next_frames()[sim]
        assert float(g.height(joints_of(x.double())).min()) > -1e-4
    crowd.remove_obstacle()
    crowd.set_ground()
    assert crowd.environment.plain
    assert math.isclose(float(joints_of(crowd.state(plain).double())[0, 0]), 3.0, abs_tol=1.0)


def _ball_frames(ball, env, frames):
    from avatar_motor.physics.simulate import _ball_hits
    far = torch.full((NUM_JOINTS, 3), 100.0, dtype=torch.float64)  # a body nowhere near the ball
    still, masses = torch.zeros(NUM_JOINTS, 3, dtype=torch.float64), torch.full((NUM_JOINTS,), 3.0, dtype=torch.float64)
    out = []
    for _ in range(frames):
        _, ball, hit = _ball_hits(far, still, masses, ball, PhysicsConfig().gravity, env)
        assert not hit
        out.append(ball)
    return out


def test_a_fast_ball_bounces_off_a_thin_turned_wall_and_does_not_pass_through():
    """15 m/s (50 cm a frame) at a wall 10 cm thick turned 30 degrees: the ball never gets behind
    it (swept test), comes back with half its speed across the wall's face (SURFACE_RESTITUTION)
    and keeps TANGENTIAL_KEPT of it along the face; without the wall it flies on."""
    from avatar_motor.physics.simulate import SURFACE_RESTITUTION, TANGENTIAL_KEPT, Ball
    wall = Box((0.0, 0.0), (3.0, 1.0, 0.1), 30.0)
    R, c, half = wall.frame()
    u0 = torch.tensor([0.0, 0.0, -15.0], dtype=torch.float64)
    ball = Ball(torch.tensor([0.0, 0.5, 1.0], dtype=torch.float64), u0.clone(), 1.0, 0.11)
    seen = _ball_frames(ball, Environment(boxes=(wall,)), 5)  # (then it would meet the floor)
    depth = [float(((b.position - c) @ R)[2]) for b in seen]  # along the wall's normal, from its middle
    assert min(depth) >= half[2] + 0.11 - 1e-9  # always on the near side, never inside or through
    w0, w1 = u0 @ R, seen[-1].velocity @ R
    assert float(w1[2]) == pytest.approx(-SURFACE_RESTITUTION * float(w0[2]), abs=1e-9)
    assert float(w1[0]) == pytest.approx(TANGENTIAL_KEPT * float(w0[0]), abs=1e-9)
    free = _ball_frames(ball, Environment(), 5)
    assert float(free[-1].position[2]) < -1.0


def test_a_ball_dropped_on_a_box_comes_to_rest_on_its_top_and_one_inside_is_put_out():
    from avatar_motor.physics.simulate import Ball
    box = Box((0.0, 0.0), (1.0, 0.8, 1.0))
    drop = Ball(torch.tensor([0.1, 1.6, 0.0], dtype=torch.float64), torch.zeros(3, dtype=torch.float64), 2.0, 0.1)
    seen = _ball_frames(drop, Environment(boxes=(box,)), 90)
    ys = torch.tensor([float(b.position[1]) for b in seen])
    assert float(ys.min()) >= 0.9 - 1e-9  # on the top (0.8 m) by its radius, never into it
    assert float(ys[-10:].max()) < 0.92 and abs(float(seen[-1].position[0]) - 0.1) < 1e-9
    inside = Ball(torch.tensor([0.45, 0.4, 0.0], dtype=torch.float64), torch.zeros(3, dtype=torch.float64), 2.0, 0.1)
    (out,) = _ball_frames(inside, Environment(boxes=(box,)), 1)
    assert float(out.position[0]) >= 0.6 - 1e-9  # through the nearest face (+x), by its radius


def test_an_obstacle_between_shields_the_avatar_from_a_ball(tmp_path):
    """In the crowd: a ball thrown at a physics avatar's chest through a wall placed between them
    bounces back off the wall (half its speed) and stays on the wall's far side from the body;
    without the wall it flies on past where the wall would be, to the body."""
    from avatar_motor.body.motion_state import joints_of
    from avatar_motor.runtime.crowd import Crowd, RuntimeConfig
    from .conftest_models import tiny_motor
    motor = tiny_motor(tmp_path)

    def run(wall):
        crowd = Crowd(motor, RuntimeConfig(), 0)
        i = crowd.spawn()
        crowd.set_physics(i, True)
        for _ in range(3):
            crowd.next_frames()
        chest = joints_of(crowd.state(i))[JOINT_INDEX["spine3"]].double()
        face = float(chest[2]) + 0.6 + 0.05  # the wall's face toward the ball: 0.6 m in front, 10 cm thick
        if wall:
            crowd.add_obstacle([float(chest[0]), float(chest[2]) + 0.6], [2.0, 2.0, 0.1])
        crowd.throw(i, (chest + torch.tensor([0.0, 0.0, 1.5], dtype=torch.float64)).tolist(), [0.0, 1.0, -12.0], mass=3.0)
        seen = []
        for _ in range(15):
            crowd.next_frames()
            seen += [(b.position[2].item(), b.velocity[2].item()) for b in crowd.balls(i)]
        return face, seen

    face, free = run(False)
    assert free and min(z for z, _ in free) < face - 0.3  # on to the body
    face, shielded = run(True)
    assert shielded and min(z for z, _ in shielded) >= face + 0.11 - 1e-6  # never into or past the wall
    assert max(v for _, v in shielded) == pytest.approx(6.0, abs=0.5)  # back at half of 12 m/s


def test_over_footprint_follows_the_box_rectangle_turned_with_it():
    """Environment.over_footprint: a point is near a box when it is over its footprint grown by
    `grow` on every side, the rectangle turned with the box (a long bar is near across its length
    only); no boxes, nothing is near."""
    bar = Box((0.0, 2.0), (2.0, 0.2, 0.15))  # 2 m along x, 15 cm deep along z
    env = Environment(boxes=(bar,))
    pts = torch.tensor([[0.0, 0.9], [0.0, 1.0], [0.9, 2.0], [1.9, 2.0], [2.1, 2.0], [0.0, 3.2]], dtype=torch.float64)
    assert env.over_footprint(pts, 1.0).tolist() == [False, True, True, True, False, False]
    turned = Environment(boxes=(Box((0.0, 2.0), (2.0, 0.2, 0.15), yaw=90.0),))  # now 2 m along z
    assert turned.over_footprint(pts, 1.0).tolist() == [True, True, True, False, False, True]
    assert not Environment().over_footprint(pts, 1.0).any()


@pytest.mark.slow  # 6 s of a compliant body with the shipped model: about half a minute here
def test_an_avatar_not_in_physics_mode_steps_over_a_low_obstacle(tmp_path):
    """RuntimeConfig.step_over: with its pelvis within step_over_reach of the footprint of an
    obstacle no higher than step_over, an avatar not in physics mode is simulated (and not near
    one, or by a command, not); a higher one stays a wall. With the shipped model, a walk at
    1.2 m/s crosses a 20 cm bar 2 m ahead with no joint of the exported body in it, and is the
    model's alone again past it; with step_over 0 the bar stops it."""
    from avatar_motor.body.motion_state import body_joints
    from avatar_motor.runtime.crowd import Crowd, RuntimeConfig
    from .conftest_models import SHIPPED, shipped_or_tiny
    motor = shipped_or_tiny(tmp_path)
    shipped = SHIPPED.joinpath("model.safetensors").exists()

    def walk(step_over, height, seconds, at=2.0, route_ahead=3.0):
        crowd = Crowd(motor, RuntimeConfig(step_over=step_over, route_ahead=route_ahead), 0)
        i = crowd.spawn()
        crowd.add_obstacle((0.0, at), (2.0, height, 0.15))
        crowd.set_goal(i, [0.0, 1.2])
        shown, simulated = [crowd.state(i)], []
        for _ in range(int(seconds * 30)):
            shown.append(crowd.next_frames()[i])
            simulated.append(crowd.avatars[i].physics)
        X = torch.stack(shown).double()
        return crowd, i, body_joints(X, rest_offsets(crowd.shape(i), torch.float64)), simulated

    crowd, i, _, simulated = walk(0.3, 1.0, 0.5, at=0.5)  # a high box: a wall, not stepped over
    assert not any(simulated)
    crowd, i, _, simulated = walk(0.3, 0.2, 0.5, at=2.8)  # a low bar 2.7 m ahead: not yet near
    assert not any(simulated)
    crowd, i, _, simulated = walk(0.3, 0.2, 0.5, at=0.5)  # a low bar, the pelvis 0.4 m from its face
    a = crowd.avatars[i]
    assert simulated[0] and a.stepping_over
    crowd.set_physics(i, False)  # a command's mode from now on: still stepped over while near it
    assert not a.stepping_over
    crowd.remove_obstacle()
    for _ in range(30):
        crowd.next_frames()
    assert not a.physics and not a.stepping_over  # nothing near: the model's alone
    if shipped:
        crowd, i, J, simulated = walk(0.3, 0.2, 6.0)
        bar = Box((0.0, 2.0), (2.0, 0.2, 0.15))
        assert any(simulated) and not simulated[0]  # simulated only near the bar
        assert float(J[-1, 0, 2]) > 3.0  # crossed
        assert not _inside(J, bar, COLLISION_RADIUS, 0.02).any()  # no sphere 2 cm into the bar
        assert not simulated[-1]  # past it: no longer simulated
        _, _, J0, _ = walk(0.0, 0.2, 4.0, route_ahead=0.0)
        assert float(J0[-1, 0, 2]) < 2.0  # without (and not routed round it): the bar is a wall


def test_a_tilting_ground_turns_at_a_constant_rate_from_the_ground_shown():
    from avatar_motor.physics.environment import GroundMotion
    m = GroundMotion(Ground((0.0, 0.0)), Ground((20.0, -10.0), (1.0, 2.0)), frame=10, frames=30)
    assert m.at(0) == m.at(10) == Ground() and m.at(40) == m.at(99) == Ground((20.0, -10.0), (1.0, 2.0))
    mid = m.at(25)
    assert mid.tilt == pytest.approx((10.0, -5.0)) and mid.pivot == pytest.approx((0.5, 1.0))
    assert not m.over(39) and m.over(40)
    env = Environment(Ground((20.0, -10.0), (1.0, 2.0))).describe(m)
    assert env["ground"]["from"] == {"tilt": [0.0, 0.0], "pivot": [0.0, 0.0], "frame": 10, "frames": 30}
    assert "from" not in Environment().describe()


def test_a_simulated_body_stands_on_a_ground_that_turns_under_it_frame_by_frame(tmp_path):
    """set_ground with seconds: the ground under a body 3 m from the pivot rises 3.6 cm a frame,
    and each frame shown meets the ground of its own frame (no joint under it, as one made on an
    older frame's ground would be); a second simulated body whose queue is longer waits for a batch of its own; the
    same commands replay bit for bit; a bad duration is named."""
    from avatar_motor.runtime.crowd import Crowd, RuntimeConfig
    from avatar_motor.serve.world import World
    from .conftest_models import SHIPPED, shipped_or_tiny
    motor = shipped_or_tiny(tmp_path)
    shipped = SHIPPED.joinpath("model.safetensors").exists()

    def run():
        crowd = Crowd(motor, RuntimeConfig(), 3)
        ids = [crowd.spawn(), crowd.spawn(position=(2.0, 0.0))]
        for i in ids:
            crowd.set_physics(i, True)
        for _ in range(10):
            crowd.next_frames()
        crowd.set_ground((20.0, 0.0), (0.0, 3.0), seconds=1.0)
        assert crowd.ground_motion is not None and crowd.ground_motion.frame == crowd.clock
        crowd.next_frames()  # (the command cut both: a segment each, made together)
        b = crowd.avatars[ids[1]]  # out of phase by 3 frames
        b.queue, b.ball_queue, b.pull_queue = b.queue[:-3], b.ball_queue[:-3], b.pull_queue[:-3]
        batches, shown = [], {i: [] for i in ids}
        real_prepare = crowd.prepare

        def prepare(n):  # each batch, with its avatars' queue lengths as it was made
            b = real_prepare(n)
            if b is not None:
                batches.append((b, {len(crowd.avatars[i].queue) for i in b.avatars}))
            return b
        crowd.prepare = prepare
        for _ in range(45):
            out = crowd.next_frames()
            for i in ids:
                shown[i].append((crowd.ground_at(crowd.clock), out[i]))
        return crowd, batches, shown

    crowd, batches, shown = run()
    turning = [(b, queued) for b, queued in batches if b.grounds is not None]
    assert turning and all(len(queued) == 1 for _, queued in turning)  # one start frame a batch
    assert any(len(b) == 1 for b, _ in turning)  # the later one waited
    for i, frames in shown.items():
        for g, x in frames:
            J = x.double()[SLICES["joints"]].reshape(22, 3)
            low = float(g.height(J).min())
            assert low > -0.005  # no joint centre under the ground of its frame

    assert shown[0][-1][0] == Ground((20.0, 0.0), (0.0, 3.0))
    crowd.reset(0)  # stood up on the tilted ground, 1.1 m above the floor here, not in it
    J = crowd.state(0).double()[SLICES["joints"]].reshape(22, 3)
    stand = standing_state().double()[SLICES["joints"]].reshape(22, 3)
    assert float(crowd.ground_at(crowd.clock).height_below(J[0, [0, 2]])) > 1.0
    assert abs(float(J[:, 1].min() - crowd.ground_at(crowd.clock).height_below(J[0, [0, 2]])) - float(stand[:, 1].min())) < 1e-5
    _, _, again = run()
    assert all(torch.equal(a[1], b[1]) for i in shown for a, b in zip(shown[i], again[i]))
    with pytest.raises(ValueError, match="seconds"):
        crowd.set_ground((5.0, 0.0), seconds=-1.0)
    w = World(motor, seed=0)
    w.apply({"type": "spawn"}, log=False)
    w.apply({"type": "ground", "tilt": [10.0, 0.0], "seconds": 2.0})
    assert w.environment_payload()["ground"]["from"]["frames"] == 60


def test_eval_physics_reads_a_tilting_platform_on_the_ground_of_each_frame(tmp_path, monkeypatch):
    """eval physics --part environment's platform rows: the ground under the standing bodies moves
    as the tilt and pivot say (10 degrees, 2 m from the pivot line: 0.35 m up), the figures are
    read against the ground of each frame, and the table prints them."""
    from avatar_motor.eval import physics as ev
    from .conftest_models import tiny_motor
    for name, value in (("BARS", ()), ("STEP_OVER_BARS", ()), ("TILTS", ()), ("PLATFORMS", ((10.0, 0.5),)), ("BEFORE", 0.3), ("AFTER", 1.0)):
        monkeypatch.setattr(ev, name, value)
    r = ev.environment_eval(tiny_motor(tmp_path), n=1, progress=lambda _: None)
    (row,) = r["platforms"]
    assert row["ground_moved_m"] == pytest.approx(math.tan(math.radians(10.0)) * ev.PLATFORM_PIVOT, abs=0.1)
    assert row["penetration_cm"] < 0.5  # no joint centre under the turning ground
    assert "tilting to 10 deg in 0.5 s" in ev.format_environment(r)
