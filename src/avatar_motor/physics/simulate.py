"""Segments of physical motion: the solver (solver.py) stepped frame by frame, its kinematic energy
the motion model's candidate segments, with what acts on the bodies from outside: forces held at a
joint, springs pulling a joint toward a point (the studio's drag), and balls.

The runtime samples K candidate segments from the frame a physics segment starts at (the model's
prediction of what this body does next, K ways) and hands them in; frame i's candidates are the
samples' frame i (DROP samples one frame ahead; a segment model gives 15 at once, so the manifold
for frame i is conditioned on the segment's start, and a perturbation cuts and resamples).

Balls are rigid spheres under gravity that bounce on the ground and off the obstacles. A ball
meets a joint's collision sphere (COLLISION_RADIUS) when their centres come within the two radii
during the frame (swept, so a fast ball does not pass through a wrist between two frames). The hit is an impulse along
the line of centres, shared as a collision of the ball with the part of the body around the hit
joint (the joints within HIT_REACH of it, their masses; the rest of the body follows through the
bones in the solve), with restitution BALL_RESTITUTION; the body takes it as a force over the frame.
DROP (§8) used penalty forces from penetration depth; at 30 frames/s a 10 m/s ball travels 33 cm
between frames, deeper than any joint sphere, so the penalty either misses it or explodes."""
from __future__ import annotations

from dataclasses import dataclass

import torch

from ..body.motion_state import FPS, finite_velocities, joints_of, pack, unpack, velocities_of
from ..runtime.processing import spring_decay
from .environment import FLAT, Environment, lift_above, push_out_of_boxes, touching
from .solver import (COLLISION_RADIUS, FLIGHT_MARGIN, H, REST_HEIGHT, Bodies, Candidates, PhysicsConfig, ballistic_candidates,
                     pose_from_particles, step)
from .wrench import correct

BALL_RESTITUTION = 0.3  # the ball keeps this share of its speed along the hit (a leather ball on a body)
SURFACE_RESTITUTION = 0.5  # and this on the ground and the obstacles
TANGENTIAL_KEPT = 0.8  # and this share of its speed along the surface it bounces off
HIT_REACH = 0.3  # m: the joints around a hit one that take the blow with it
PLANTED_MARGIN = 0.07  # m above its resting height a joint counts as on the ground (no carried pull)


@dataclass
class Ball:
    """A projectile in the world frame."""
    position: torch.Tensor  # (3,) m
    velocity: torch.Tensor  # (3,) m/s
    mass: float  # kg
    radius: float  # m

    def validate(self) -> None:
        for name in ("position", "velocity"):
            t = getattr(self, name)
            if t.shape != (3,) or not torch.isfinite(t).all():
                raise ValueError(f"ball {name} must be 3 finite numbers, got {t.tolist()}")
        if not (0.01 <= self.mass <= 100.0):
            raise ValueError(f"ball mass must be 0.01..100 kg, got {self.mass}")
        if not (0.02 <= self.radius <= 1.0):
            raise ValueError(f"ball radius must be 0.02..1 m, got {self.radius}")


@dataclass
class Spring:
    """A joint pulled toward a world point: force = stiffness (target - joint) - damping v_joint."""
    joint: int
    target: torch.Tensor  # (3,) m
    stiffness: float = 400.0  # N/m
    damping: float = 40.0  # N s/m


def _off_boxes(p: torch.Tensor, u: torch.Tensor, dt: float, radius: float, boxes: tuple) -> tuple[torch.Tensor, torch.Tensor]:
    """A ball at p (3,) moving at u (3,) for dt s, against the obstacles (environment.Box): where it
    is at the end and its velocity. Swept, so that a fast ball does not pass through a thin bar in
    a frame: the path is cut with each box grown by the radius (the slab test in the box's frame;
    a rounded box's corners taken as square), and at the first face it meets the ball bounces
    (SURFACE_RESTITUTION across the face, TANGENTIAL_KEPT along it) and travels the rest of dt (a
    second box in that rest is not looked at). A ball already inside a box (one placed onto it)
    leaves through its nearest face."""
    first = None  # (time share, face axis, side, the hit point in box coordinates, the box's frame)
    for box in boxes:
        q0, e, R, c = box.local(p[None], torch.tensor([radius], dtype=p.dtype))  # box coordinates, grown box
        q0, e = q0[0], e[0]
        d = (u @ R) * dt
        if bool((q0.abs() < e).all()):
            axis = int((e - q0.abs()).argmin())
            side = 1.0 if float(q0[axis]) >= 0 else -1.0
            q_hit = q0.clone()
            q_hit[axis] = side * e[axis]
            first = (0.0, axis, side, q_hit, R, c, e)
            break
        safe = torch.where(d.abs() > 1e-12, d, torch.full_like(d, 1e-12))
        t1, t2 = (-e - q0) / safe, (e - q0) / safe
        near, far = torch.minimum(t1, t2), torch.maximum(t1, t2)
        still = d.abs() <= 1e-12  # not moving along an axis: inside that slab always, or never
        near = torch.where(still, torch.where(q0.abs() < e, -torch.inf, torch.inf), near)
        far = torch.where(still, torch.where(q0.abs() < e, torch.inf, -torch.inf), far)
        t_in, t_out = float(near.max()), float(far.min())
        if t_in <= t_out and 0.0 <= t_in <= 1.0 and (first is None or t_in < first[0]):
            axis = int(near.argmax())
            q_hit = q0 + t_in * d
            first = (t_in, axis, 1.0 if float(q_hit[axis]) >= 0 else -1.0, q_hit, R, c, e)
    if first is None:
        return p + dt * u, u
    t_hit, axis, side, q_hit, R, c, e = first
    w = u @ R
    if float(w[axis]) * side < 0:  # moving into the face: bounce
        across = -SURFACE_RESTITUTION * w[axis]
        w = TANGENTIAL_KEPT * w
        w[axis] = across
    q = q_hit + (1.0 - t_hit) * dt * w
    q[axis] = side * max(side * float(q[axis]), float(e[axis]))  # not back into the box
    return q @ R.T + c, w @ R.T


def _ball_hits(x: torch.Tensor, v: torch.Tensor, masses: torch.Tensor, ball: Ball, g: float,
               env: Environment = FLAT) -> tuple[torch.Tensor, Ball, bool]:
    """One frame of a ball against one body: joints x (22, 3), velocities v (22, 3), masses (22,),
    in the environment env (the ground and the obstacles). Returns the force (22, 3) the body
    takes over the frame, the ball a frame later, and whether it hit."""
    f = torch.zeros_like(x)
    p, u = ball.position.to(x.dtype), ball.velocity.to(x.dtype)
    # the swept test: when during the frame the ball's sphere first touches each joint's, both
    # moving straight: |rel_p + t rel_v| = r_joint + r_ball, the smaller root
    rel_p, rel_v = p - x, u - v  # (22, 3)
    reach = COLLISION_RADIUS.to(x.dtype) + ball.radius
    qa = (rel_v * rel_v).sum(-1).clamp_min(1e-12)
    qb = (rel_p * rel_v).sum(-1)
    qc = (rel_p * rel_p).sum(-1) - reach**2
    disc = qb**2 - qa * qc
    t = torch.where(qc <= 0, torch.zeros_like(qc), (-qb - disc.clamp_min(0).sqrt()) / qa)
    touches = (disc >= 0) & (t >= 0) & (t <= H) & (qb < 0)  # and closing in
    hit_any = bool(touches.any())
    if hit_any:
        hit = int(torch.where(touches, t, torch.full_like(t, float("inf"))).argmin())
        s = float(t[hit])
        at = rel_p[hit] + s * rel_v[hit]
        n = at / at.norm().clamp_min(1e-9)  # from the joint to the ball at contact
        near = (x - x[hit]).norm(dim=-1) <= HIT_REACH
        m_body = float(masses[near].sum())
        closing = -float((rel_v[hit] * n).sum())
        J = (1 + BALL_RESTITUTION) * max(closing, 0.0) / (1 / ball.mass + 1 / m_body)  # N s, along -n on the body
        f[hit] = -J * n / H
        p = p + s * u  # to the contact, then away with the new velocity
        u = u + (J / ball.mass) * n
        rest = H - s
    else:
        rest = H
    p, u = _off_boxes(p, u, rest, ball.radius, env.boxes) if env.boxes else (p + rest * u, u)
    u = u - torch.tensor([0.0, g * H, 0.0], dtype=x.dtype)
    ground = env.ground
    n = ground.normal(x.dtype)
    if float(ground.height(p)) < ball.radius:  # the ground: back onto it, bouncing off along its normal
        p = p + (ball.radius - ground.height(p)) * n
        along = (u * n).sum()
        if float(along) < 0:
            u = TANGENTIAL_KEPT * (u - along * n) - SURFACE_RESTITUTION * along * n
    return f, Ball(p.to(ball.position.dtype), u.to(ball.velocity.dtype), ball.mass, ball.radius), hit_any


def segment(bodies: Bodies, x0: torch.Tensor, cands: torch.Tensor, cfg: PhysicsConfig | None = None, rom=None,
            forces: torch.Tensor | None = None, springs: list[list[Spring]] | None = None,
            balls: list[list[Ball]] | None = None, trace: list | None = None,
            correcting: list[bool] | None = None, env: Environment = FLAT,
            goals: tuple[torch.Tensor, torch.Tensor] | None = None,
            pull: torch.Tensor | None = None, holding: torch.Tensor | None = None,
            grounds: tuple | None = None) -> tuple[torch.Tensor, list[list[list[Ball]]], torch.Tensor, list[int], torch.Tensor]:
    """Physical frames for B bodies from their states x0 (B, 267) (world): candidates (B, K, N, 267)
    one-body world frames sampled from the model (frame i of each is the kinematic energy's set
    for frame i); forces (B, N, 22, 3) N per frame, or None; springs and balls: per body, lists.
    Returns the frames (B, N, 267) as one body each (rotations: swing from the solved bones, twist
    from the candidate chosen; joints: FK of them; velocities: differences), each body's balls
    after each frame [body][frame][ball], the index (B, N) of the candidate chosen at each frame,
    and each body's length: the frames to keep before sampling again (cfg.resample_distance; a
    hit ends the segment after the frame it lands in). All N frames are made either way.
    trace: a list each frame's energies (solver.energies) are appended to. correcting: the bodies
    the soft correction runs for (None: all, when cfg.correction > 0). env: the ground and the
    obstacles. goals: goal velocities (B, 3) m/s and the weight (B,) of the centre-of-mass velocity
    energy toward them (0 for a body without a goal), or None. pull (B, 22, 3): how the kinematic
    energy pulled each joint at the frame x0 is (its weight times its target minus the body, as
    returned for the segment before), or None. The candidates start at the body, so at a join that
    pull would vanish at once (a jerk twice a second); it is carried into the candidates instead
    and decays (cfg.pull_halflife), but for the joints on the ground at x0 (PLANTED_MARGIN), which
    would skate. A body whose weight changed at the join (bodies.kinematic: calm or not) keeps the
    pull's strength, not its distance: a stiff body does not jump to where a compliant one was
    pulled. A compliant body in flight is carried by gravity and the external forces alone
    (solver.ballistic_candidates). Also returns each frame's pull (B, N, 22, 3), weight times
    distance. holding (B,) bool: the bodies held up by cfg.held_weight of their weight while not in
    flight (undisturbed compliant ones), or None: none. grounds: the ground of each frame (N
    environment.Ground; a tilting platform), or None: env's throughout."""
    cfg = cfg or PhysicsConfig()
    B, K, N, _ = cands.shape
    x = joints_of(x0.double())
    v = velocities_of(x0.double())
    u0 = unpack(x0.double())
    pose = (u0.root_rot, u0.local_rot)  # x's rotations, which the range of motion reads
    cu = unpack(cands.double())
    springs = springs or [[] for _ in range(B)]
    balls = [list(b) for b in (balls or [[] for _ in range(B)])]
    out_root, out_rot, out_local, out_J, chosen, ball_frames = [], [], [], [], [], [[] for _ in range(B)]
    lengths = [N] * B
    pulls = []
    w = bodies.kinematic.to(torch.float64)[:, None, None]
    if grounds is not None and len(grounds) != N:
        raise ValueError(f"grounds: one per frame, {N}, got {len(grounds)}")
    envs = [env] * N if grounds is None else [Environment(g, env.boxes) for g in grounds]
    if pull is not None:  # a joint on the ground keeps its footing: its pull is not carried (skating)
        planted = envs[0].ground.height(x) < REST_HEIGHT.to(x.dtype) + PLANTED_MARGIN
        pull = torch.where(w > 0, pull.double() / w.clamp_min(1e-9), 0.0) * (~planted)[..., None]
    # the carried pull's share at each frame: a critically damped decay from 1, at rest
    carried = spring_decay(torch.ones(()), torch.zeros(()), cfg.pull_halflife,
                           torch.arange(1, N + 1, dtype=torch.float64) * H) if pull is not None else None
    drift = torch.zeros(B, 3, dtype=torch.float64)  # the candidates' shift by the body's flights so far
    contact_forces = None  # the frame before's (wrench.correct), which spare most frames the NNLS
    correcting = [True] * B if correcting is None else list(correcting)
    for i in range(N):
        env = envs[i]
        hit = [False] * B
        f = torch.zeros(B, 22, 3, dtype=torch.float64) if forces is None else forces[:, i].double().clone()
        for b in range(B):
            for sp in springs[b]:
                f[b, sp.joint] += sp.stiffness * (sp.target.double() - x[b, sp.joint]) - sp.damping * v[b, sp.joint]
            moved = []
            for ball in balls[b]:
                fb, ball, struck = _ball_hits(x[b], v[b], bodies.masses[b], ball, cfg.gravity, env)
                f[b] += fb
                hit[b] |= struck
                moved.append(ball)
            balls[b] = moved
            ball_frames[b].append(list(moved))
        targets = cu.joints[:, :, i]
        if pull is not None:
            targets = targets + carried[i] * pull[:, None]
        # a body in flight is carried by gravity and the external forces only (nor does a goal
        # velocity push it); its distance from the candidates, which ends the segment, is taken
        # from what pulls it. Where the flight took it is kept: the candidates that follow are
        # shifted by it (drift), so a landed body is not pulled back to where they hovered
        # (without, 8 hit avatars resampled every 6 frames instead of 15, at 0.6-0.8x real time,
        # and a compliant walker hovered in 34 % of its frames; with it 16 %)
        targets = targets + drift[:, None, None]
        moved, flight = ballistic_candidates(bodies, x, v, targets, f, cfg, env)
        if flight is not None:
            drift = drift + (moved - targets)[:, :, 0].mean(1)  # each candidate shifted as one piece
        targets = moved
        goal = goals if flight is None or goals is None else (goals[0], goals[1] * (1 - flight))
        c = Candidates(targets, cu.root_rot[:, :, i], cu.local_rot[:, :, i])
        if holding is not None and cfg.held_weight > 0 and bool(holding.any()):  # the weight the model's muscles carry
            # (only through a joint on the ground or an obstacle: a body in the air is not held)
            held = (holding & touching(x, REST_HEIGHT, COLLISION_RADIUS, env, FLIGHT_MARGIN)).to(torch.float64) * cfg.held_weight
            f[..., 1] += held[:, None] * bodies.masses * cfg.gravity
        solved, _, k = step(bodies, x, v, c, forces=f, cfg=cfg, rom=rom, env=env, trace=trace, pose=pose, goal=goal)
        if cfg.correction > 0 and any(correcting):  # no force the ground cannot give (DROP §6)
            solved, _, _, contact_forces = correct(solved, x, v, bodies.masses, f, cfg, contact_forces, correcting)
        rows = torch.arange(B)
        off = c.joints[rows, k] - solved
        pulls.append(w * off)
        off = (off ** 2).sum(-1)  # (B, 22)
        apart = ((off * bodies.masses).sum(-1) / bodies.masses.sum(-1)).sqrt()
        for b in range(B):
            if lengths[b] == N and (hit[b] or float(apart[b]) > cfg.resample_distance):
                lengths[b] = i + 1
        root_pos, root_rot, local, J = pose_from_particles(solved, c.root_rot[rows, k], c.local_rot[rows, k], bodies.offsets)
        # rigid bones can put a joint the particles held above the ground under it (a toe up to
        # 4.6 cm in 0.2 % of frames): the frame is lifted onto it, as the kinematic runtime does
        if cfg.contact > 0:  # (off with the contact energy: that ablation shows what it holds)
            # (and out of the obstacles: the solved particles were, but the body on its rest-length
            # bones from the pelvis can put a foot 3-8 cm into a low bar)
            up = lift_above(J, env.ground)
            if env.boxes:
                up = up + push_out_of_boxes(J + up[:, None], COLLISION_RADIUS, env)
            root_pos, J = root_pos + up, J + up[:, None]
        pose = (root_rot, local)
        out_root.append(root_pos)
        out_rot.append(root_rot)
        out_local.append(local)
        out_J.append(J)
        chosen.append(k)
        # the next frame starts from the body that is shown (FK of its rotations)
        x, v = J, (J - x) / H
    J = torch.stack(out_J, 1)
    vel = finite_velocities(J, FPS, first=(J[:, 0] - joints_of(x0.double())) * FPS)
    frames = pack(torch.stack(out_root, 1), torch.stack(out_rot, 1), torch.stack(out_local, 1), J, vel)
    return frames, ball_frames, torch.stack(chosen, 1), lengths, torch.stack(pulls, 1)
