"""DROP's minimal physics body (Jiang et al. 2023, §4-5): particles at the 22 joints, stepped by an
implicit-Euler variational integrator solved with projective dynamics.

    x_{t+1} = argmin_x 1/(2h^2) (x - y)^T M (x - y) + sum_i w_i/2 |A_i x - p_i|^2,
    y = x_t + h v_t + h^2 M^-1 f_t + h^2 g                                          (DROP Eq. 1-4)

Local step: each energy projects the current iterate onto its set (p_i). Global step: the
quadratic in x is solved with every p_i fixed. The energies here:
- momentum (above), M the joints' anthropometric masses;
- rigidity: every bone's vector x_j - x_parent pulled to its rest length along its current
  direction (the fast mass-spring form of DROP Eq. 5);
- ground contact: a joint below the height at which it rests on the ground is projected up to
  it, at its horizontal place of the frame before (static friction, DROP Eq. 6), or, for a
  compliant body, no further back along the ground than Coulomb's law allows (the slip beyond
  `friction` times the depth is kept: its pull along the ground at most `friction` times its push up);
- range of motion: the pose of the frame the step starts from with each joint's rotation moved
  into the data's range (physics/limits.py), back through FK; that move, applied to each iterate,
  is its projection (E_RoM, lagged by one frame: see `step`);
- after the iterations the ground is also kept as a hard constraint (a last contact projection);
  the ground may be tilted and obstacles stand on it (physics/environment.py): the same projection;
- centre-of-mass velocity (DROP Eq. 16), for a body with a goal velocity: the step's momentum
  pulled toward the goal's (`com_pull`); a rank-one term, solved with the same factor;
- kinematic: the nearest of K next frames sampled from the motion model (DROP Eq. 10): the model
  is the body's control. The candidates are the caller's (this room samples no network).

Every energy keeps the same weight in every step, and a constraint that holds projects the
iterate onto itself (Bouaziz et al. 2014): so the system matrix depends only on the body, and
is factored once per body (Cholesky) and reused by every iteration of every step. All energies
are isotropic in x, y and z, so the 66 x 66 system is three 22 x 22 systems sharing one factor.

Weights are stiffnesses relative to momentum: an energy of weight w on joint j adds w m_j / h^2
to the matrix (rigidity: w times the lighter end's mass), so the body's response does not depend
on its total mass; only external forces (N, N s) do.

Pure functions on batched tensors (B bodies); the runtime holds the state and the candidates."""
from __future__ import annotations

from dataclasses import dataclass

import torch

from ..body import rotations as rot
from ..body.motion_state import FPS, horizontal
from ..body.skeleton import FOOT_CLEARANCE, JOINT_INDEX, NUM_JOINTS, PARENTS, forward_kinematics
from . import environment, limits
from .environment import OBSTACLE_CLEARANCE, FLAT, Environment

BONES = torch.tensor([(PARENTS[j], j) for j in range(1, NUM_JOINTS)])  # (21, 2): parent, child

# Share of the body's mass lumped at each joint: de Leva's (1996) segment masses (male adult,
# % of body mass: head+neck 6.94, trunk 43.46, upper arm 2.71, forearm 1.62, hand 0.61, thigh
# 14.16, shank 4.33, foot 1.37), each segment's split evenly between the joints it spans, the
# hand lumped at the wrist, the trunk spread over pelvis, spine and collars.
_SEGMENTS = [  # (mass %, joints it is lumped at)
    (11.17, ("pelvis",)), (16.33, ("spine1", "spine2")), (13.96, ("spine3",)),
    (1.0, ("left_collar",)), (1.0, ("right_collar",)), (6.94, ("neck", "head")),
]
for _side in ("left", "right"):
    _SEGMENTS += [(14.16, (f"{_side}_hip", f"{_side}_knee")), (4.33, (f"{_side}_knee", f"{_side}_ankle")),
                  (1.37, (f"{_side}_ankle", f"{_side}_foot")), (2.71, (f"{_side}_shoulder", f"{_side}_elbow")),
                  (1.62, (f"{_side}_elbow", f"{_side}_wrist")), (0.61, (f"{_side}_wrist",))]


def _mass_shares() -> torch.Tensor:
    m = torch.zeros(NUM_JOINTS, dtype=torch.float64)
    for pct, joints in _SEGMENTS:
        for name in joints:
            m[JOINT_INDEX[name]] += pct / len(joints)
    return m / m.sum()


MASS_SHARE = _mass_shares()  # (22,), sums to 1

# Radius (m) of each joint's collision sphere (the studio draws the same spheres); a joint rests
# on the ground when its centre is this high. A foot joint stands at FOOT_CLEARANCE (the data's).
COLLISION_RADIUS = torch.tensor([0.09, 0.075, 0.075, 0.08, 0.06, 0.06, 0.08, 0.045, 0.045, 0.09, 0.035, 0.035,
                                 0.05, 0.05, 0.05, 0.11, 0.05, 0.05, 0.04, 0.04, 0.035, 0.035], dtype=torch.float64)
REST_HEIGHT = COLLISION_RADIUS.clone()
REST_HEIGHT[[JOINT_INDEX["left_foot"], JOINT_INDEX["right_foot"]]] = FOOT_CLEARANCE
# The height below which the contact energy holds a calm body's joint (PhysicsJob.calm): its
# resting height, but the foot (toe) joints go down to the ground itself, as the model's motion
# does when a foot rolls over its toes (the kinematic runtime's frames put them below
# FOOT_CLEARANCE in 11 % of frames, never below 0). Held at FOOT_CLEARANCE, a rolling toe was
# pinned where it was and the foot turned off the model's pose (eval realism --physics, seed 1:
# naturalness 1.67 -> 1.52). A compliant body stands on REST_HEIGHT: its toes grip at 2 cm.
CALM_CONTACT_HEIGHT = REST_HEIGHT.clone()
CALM_CONTACT_HEIGHT[[JOINT_INDEX["left_foot"], JOINT_INDEX["right_foot"]]] = 0.0
# m above its resting height a joint still touches the ground (or an obstacle); a body with no
# such joint is in flight (PhysicsConfig.ballistic). Real motion always has one: in 64 held-out
# Bandai windows the lowest joint is at most 1.7 cm above its resting height (99th percentile);
# a compliant walker held up by its prior had none in a third of its frames
FLIGHT_MARGIN = 0.03


@dataclass
class PhysicsConfig:
    mass: float = 70.0  # kg, the whole body
    iterations: int = 3  # local/global iterations per step (DROP §7)
    rigidity: float = 50.0  # bone springs
    contact: float = 3.0  # ground (DROP w2)
    range_of_motion: float = 3.0  # joint limits (DROP w3)
    kinematic: float = 3.0  # the motion model's nearest candidate (DROP w_kin), for a body something acts on
    # ... and for a calm body: nothing from outside (a push, force, spring or ball) for the runtime's
    # SETTLE seconds, on a flat floor with no obstacle near. Stiff and with one candidate, the body
    # follows the model as the kinematic runtime does (DROP's weight left it drifting off the data);
    # hit, it turns compliant, and the weight above gives the physical response (docs/physics.md)
    kinematic_calm: float = 30.0
    candidates_calm: int = 1
    # a goal velocity's pull on the centre of mass (DROP Eq. 16; 0: off): as strong as the prior's,
    # it helps a run keep up without pulling a walk off its feet (docs/physics.md)
    com_velocity: float = 3.0
    gravity: float = 9.81  # m/s^2, along -y
    candidates: int = 8  # next frames sampled from the model per body (DROP's K)
    # a segment ends early (and the next is sampled from where the body is) once a ball hits or the
    # solved body is this far (m, mass-weighted RMS over the joints) from every candidate: the
    # candidates were drawn at the segment's start and no longer describe this body
    resample_distance: float = 0.08
    # s: the kinematic energy's pull on a body at a segment's end is carried into the next
    # segment's candidates and decays with this half-life (simulate.segment)
    pull_halflife: float = 0.1
    # DROP §6: after each step, a frame whose root-wrench metric (force no ground contact can give)
    # is above `ghost_threshold` body weights is moved the least that removes most of it (the
    # weight w of Eq. 14, e.g. 1e-5; 0: off). The threshold is what real held-out motion reaches
    # (its 95th percentile, `eval physics`: 0.14); `friction` is the contacts' coefficient. Off by
    # default: on, the metric rose instead (eval physics, 8 rollouts: 95th percentile 0.15 -> 0.36
    # unperturbed, 0.43 -> 0.76 after a 200 N s push; ASR 0.028 -> 0.058): the candidates, drawn
    # at the segment's start, pull the corrected body back harder at the next frame
    correction: float = 0.0
    # the share of the prior's net force taken away from a compliant body in flight (no joint
    # within FLIGHT_MARGIN of the ground or an obstacle at the frame it steps from): gravity and
    # the external forces alone move its centre of mass, as they do a real body's in the air
    # (1: all; 0: the prior holds it up). After a push the candidates had carried bodies whose feet
    # had left the ground; with it the root-wrench metric's 95th percentile after 50-400 N s fell
    # from 0.49-1.13 to 0.27-0.70 body weights (eval physics, docs/physics.md). A calm body keeps
    # the model's hold (with the rule its jitter rose 1.12 -> 1.43)
    ballistic: float = 1.0
    # the share of its weight an undisturbed compliant body (one near an obstacle, nothing acting
    # on it) is held up by, as an upward force on each joint while it is not in flight: the
    # prior's pull alone let it sag frame after frame, and its next candidates, drawn from the
    # sagging body, went on lower (past a 20-cm bar the pelvis at 0.86-0.92 m, walking beside a bar
    # the head 1.27-1.51 m, against 0.97 and 1.58 in the open; held, 0.92-0.97 and 1.46-1.53). The
    # ground gives that force through the feet. A body something acts on is not held: after a
    # 400 N s push the root-wrench metric's 95th percentile rose 0.49 -> 0.70 when it was
    held_weight: float = 1.0
    correction_step: float = 0.01  # m: the most a correction moves any joint in a frame
    ghost_threshold: float = 0.15
    # the ground's Coulomb coefficient: a compliant body's contacts (a calm body's feet are held
    # where the model plants them) and the friction pyramids of the root-wrench metric
    friction: float = 0.8

    def validate(self) -> None:
        for name in ("mass", "rigidity", "contact", "range_of_motion", "kinematic", "kinematic_calm", "com_velocity", "gravity", "correction",
                     "correction_step", "ghost_threshold", "friction", "ballistic", "held_weight"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and v >= 0 and v == v and v != float("inf")):
                raise ValueError(f"physics {name} must be a finite number >= 0, got {v!r}")
        if self.mass <= 0:
            raise ValueError(f"physics mass must be > 0 kg, got {self.mass!r}")
        if not (isinstance(self.iterations, int) and 1 <= self.iterations <= 100):
            raise ValueError(f"physics iterations must be an integer 1..100, got {self.iterations!r}")
        for name in ("candidates", "candidates_calm"):
            v = getattr(self, name)
            if not (isinstance(v, int) and 1 <= v <= 64):
                raise ValueError(f"physics {name} must be an integer 1..64, got {v!r}")
        if self.ballistic > 1:
            raise ValueError(f"physics ballistic must be a share 0..1, got {self.ballistic!r}")
        if not (self.pull_halflife > 0):
            raise ValueError(f"physics pull_halflife must be > 0 s, got {self.pull_halflife!r}")
        if not (self.resample_distance > 0):
            raise ValueError(f"physics resample_distance must be > 0 m, got {self.resample_distance!r}")


@dataclass
class Bodies:
    """What the solver keeps per body: bones, masses, rest lengths and the factored system."""
    offsets: torch.Tensor  # (B, 22, 3) the body's bones
    masses: torch.Tensor  # (B, 22) kg
    rest: torch.Tensor  # (B, 21) m
    factor: torch.Tensor  # (B, 22, 22) lower Cholesky factor of the per-axis system matrix
    matrix: torch.Tensor  # (B, 22, 22) the system matrix itself (tests compare against it)
    kinematic: torch.Tensor  # (B,) each body's kinematic weight (PhysicsConfig.kinematic or kinematic_calm)
    contact_height: torch.Tensor  # (B, 22) where the ground holds each joint (REST_HEIGHT or CALM_CONTACT_HEIGHT)
    calm: torch.Tensor  # (B,) bool: the body follows the model stiffly (prepare's calm)
    friction: torch.Tensor  # (B,) the ground contact's Coulomb coefficient (inf: static, a calm body's)


H = 1.0 / FPS  # the time step: one frame of the motion model


def _incidence(dtype) -> torch.Tensor:
    """(21, 22): row b is +1 at bone b's child and -1 at its parent, so G x = the bone vectors."""
    G = torch.zeros(NUM_JOINTS - 1, NUM_JOINTS, dtype=dtype)
    G[torch.arange(NUM_JOINTS - 1), BONES[:, 1]] = 1.0
    G[torch.arange(NUM_JOINTS - 1), BONES[:, 0]] = -1.0
    return G


def _bone_weights(masses: torch.Tensor, cfg: PhysicsConfig) -> torch.Tensor:
    """(B, 21) each bone spring's weight: rigidity x its lighter end's mass / h^2."""
    return cfg.rigidity * torch.minimum(masses[:, BONES[:, 0]], masses[:, BONES[:, 1]]) / H**2


def _diagonal(masses: torch.Tensor, cfg: PhysicsConfig, kinematic: torch.Tensor) -> torch.Tensor:
    """(B, 22) the diagonal terms: momentum, ground, range-of-motion and kinematic energies (each
    body's kinematic weight (B,)), mass-weighted."""
    return masses * (1.0 + cfg.contact + cfg.range_of_motion + kinematic[:, None]) / H**2


def prepare(offsets: torch.Tensor, cfg: PhysicsConfig | None = None, calm: torch.Tensor | None = None) -> Bodies:
    """The solver's constants for bodies with bones `offsets` (B, 22, 3): masses, rest lengths,
    and the system matrix M/h^2 + sum_i w_i A_i^T A_i per axis, factored once. calm (B,) bool:
    the bodies whose kinematic energy has the calm weight and whose toes meet the ground at
    CALM_CONTACT_HEIGHT (None: none)."""
    cfg = cfg or PhysicsConfig()
    cfg.validate()
    offsets = offsets.to(torch.float64)
    B = len(offsets)
    masses = (cfg.mass * MASS_SHARE).expand(B, NUM_JOINTS).clone()
    rest = offsets[:, 1:].norm(dim=-1)
    kinematic = torch.full((B,), float(cfg.kinematic), dtype=torch.float64)
    if calm is not None:
        kinematic[calm] = float(cfg.kinematic_calm)
    G = _incidence(torch.float64)
    A = torch.diag_embed(_diagonal(masses, cfg, kinematic)) + G.T @ (_bone_weights(masses, cfg)[:, :, None] * G)
    height = REST_HEIGHT.expand(B, NUM_JOINTS).clone()
    # a compliant body's feet slip when the ground cannot hold them (Coulomb, cfg.friction); a
    # calm body's are held where the model plants them, as the kinematic runtime's are
    friction = torch.full((B,), float(cfg.friction), dtype=torch.float64)
    if calm is not None:
        height[calm] = CALM_CONTACT_HEIGHT
        friction[calm] = float("inf")
    return Bodies(offsets, masses, rest, torch.linalg.cholesky(A), A, kinematic, height,
                  torch.zeros(B, dtype=torch.bool) if calm is None else calm.clone(), friction)


def project_bones(x: torch.Tensor, rest: torch.Tensor) -> torch.Tensor:
    """(B, 21, 3): each bone's current vector (child - parent of x (B, 22, 3)) scaled to its rest
    length (B, 21): the nearest rigid bone. A collapsed bone keeps its length along +y."""
    d = x[:, BONES[:, 1]] - x[:, BONES[:, 0]]
    n = d.norm(dim=-1, keepdim=True)
    up = torch.tensor([0.0, 1.0, 0.0], dtype=x.dtype)
    return torch.where(n > 1e-9, d / n.clamp_min(1e-12), up) * rest[..., None]


def project_ground(x: torch.Tensor, x_prev: torch.Tensor, env: Environment = FLAT,
                   height: torch.Tensor | None = None, friction: torch.Tensor | None = None) -> torch.Tensor:
    """(B, 22, 3) the contact energy's projection: a joint of x below its contact height (height
    (B, 22) above the ground plane; None: REST_HEIGHT) moved onto it at its place in x_prev, the
    frame before, unless it slipped further than the Coulomb coefficient friction (B,) times its
    depth allows (None: static friction; environment.project_ground); a joint inside an obstacle
    moved out through the face it came in by (physics/environment.py); any other joint is itself
    (no energy)."""
    height = REST_HEIGHT if height is None else height
    return environment.project_contact(x, x_prev, height, COLLISION_RADIUS, env, friction)


@dataclass
class Candidates:
    """K next frames per body sampled from the motion model, as one body each (world frame)."""
    joints: torch.Tensor  # (B, K, 22, 3)
    root_rot: torch.Tensor  # (B, K, 3, 3)
    local_rot: torch.Tensor  # (B, K, 21, 3, 3)


def project_prior(x: torch.Tensor, candidates: torch.Tensor, masses: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The candidate next frames (B, K, 22, 3) nearest to x (B, 22, 3) in the mass-weighted
    distance the energy uses; returns it (B, 22, 3) and its index (B,)."""
    d = (((candidates - x[:, None]) ** 2).sum(-1) * masses[:, None]).sum(-1)  # (B, K)
    k = d.argmin(1)
    return candidates[torch.arange(len(x)), k], k


def rigid_part(d: torch.Tensor, x: torch.Tensor, masses: torch.Tensor) -> torch.Tensor:
    """(B, 22, 3): the rigid motion (a translation t and a small rotation w about the centre of
    mass) that best fits the displacements d (B, 22, 3) of the joints x (B, 22, 3), mass-weighted.
    d less it has no net force and no net torque about the centre of mass: sum m (d - fit) = 0 and
    sum m r x (d - fit) = 0 (t: the mass-weighted mean of d; w = I^-1 sum m r x d, I the inertia
    tensor of the particles)."""
    m = masses[..., None]
    r = x - (m * x).sum(1, keepdim=True) / m.sum(1, keepdim=True)
    t = (m * d).sum(1) / masses.sum(-1)[:, None]
    L = (m * torch.linalg.cross(r, d - t[:, None])).sum(1)
    rr = (r * r).sum(-1)[..., None, None] * torch.eye(3, dtype=x.dtype) - r[..., :, None] * r[..., None, :]
    inertia = (m[..., None] * rr).sum(1) + 1e-9 * torch.eye(3, dtype=x.dtype)
    w = torch.linalg.solve(inertia, L[..., None])[..., 0]
    return t[:, None] + torch.linalg.cross(w[:, None].expand_as(r), r)


def in_flight(bodies: Bodies, x: torch.Tensor, env: Environment, cfg: PhysicsConfig) -> torch.Tensor | None:
    """(B,) the share of the prior's net force taken away from each body at x (B, 22, 3)
    (PhysicsConfig.ballistic for a compliant body with no joint within FLIGHT_MARGIN of the
    ground or an obstacle, on a flat ground and OBSTACLE_CLEARANCE from any obstacle; else 0), or
    None when no body flies."""
    if cfg.ballistic <= 0:
        return None
    flying = ~bodies.calm & ~environment.touching(x, REST_HEIGHT, COLLISION_RADIUS, env, FLIGHT_MARGIN)
    if not env.plain:  # on a slope or near an obstacle the model keeps its hold: a body stepping over
        # a bar dropped its foot into it (the studio's bar test failed in 2 of 6 runs, 0 of 5 without)
        flying &= env.plain_near(x[:, 0, [0, 2]], OBSTACLE_CLEARANCE)
    return cfg.ballistic * flying.to(x.dtype) if bool(flying.any()) else None


def ballistic_candidates(bodies: Bodies, x: torch.Tensor, v: torch.Tensor, cands: torch.Tensor,
                         forces: torch.Tensor | None, cfg: PhysicsConfig,
                         env: Environment = FLAT) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The candidate frames cands (B, K, 22, 3) for bodies at x, v (B, 22, 3), each shifted so
    that, for a body in flight (`in_flight`), its centre of mass is the inertial target's (gravity
    and the external forces (B, 22, 3) N): the pull then has no net force, and the prior shapes
    a body in the air but does not carry it. Others are returned as they are. Also returns
    `in_flight`'s shares (B,), or None. (Taking out the pull's net torque too read the same in
    `eval physics` but turned the candidates away from the body, whose segments then ended
    sooner: 8 hit avatars ran at 34 frames/s against 58.)"""
    flight = in_flight(bodies, x, env, cfg)
    if flight is None:
        return cands, None
    y = inertial_target(x.to(torch.float64), v.to(torch.float64), None if forces is None else forces.to(torch.float64),
                        bodies.masses, cfg)
    share = (bodies.masses / bodies.masses.sum(-1, keepdim=True))[:, None, :, None]
    gap = ((cands.to(y.dtype) - y[:, None]) * share).sum(2, keepdim=True)  # (B, K, 1, 3) each centre's from y's
    return cands - (flight[:, None, None, None] * gap).to(cands.dtype), flight


def range_shift(x: torch.Tensor, root_rot: torch.Tensor, local: torch.Tensor, offsets: torch.Tensor, rom) -> torch.Tensor:
    """(B, 22, 3): how far each joint of the body x (FK of root_rot (B, 3, 3) and local (B, 21, 3, 3)
    on offsets from its pelvis) moves when its rotations are moved into the range of motion; zero
    for a pose within range."""
    inside, _ = forward_kinematics(x[:, 0], root_rot.to(x.dtype), limits.project(local, rom), offsets.to(x.dtype))
    return inside - x


def inertial_target(x: torch.Tensor, v: torch.Tensor, forces: torch.Tensor | None, masses: torch.Tensor,
                    cfg: PhysicsConfig) -> torch.Tensor:
    """y = x + h v + h^2 M^-1 f + h^2 g: where the joints go without internal energies.
    forces (B, 22, 3) N, or None."""
    y = x + H * v
    y[..., 1] -= H**2 * cfg.gravity
    if forces is not None:
        y = y + H**2 * forces / masses[..., None]
    return y


def com_pull(masses: torch.Tensor, x: torch.Tensor, goal: torch.Tensor, weight: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """DROP's centre-of-mass velocity energy (Eq. 16) for bodies at x (B, 22, 3) with goal
    velocities goal (B, 3) m/s, as c (B, 22) and t (B, 3) with E_com = 1/2 |c^T x' - t|^2 on each
    horizontal axis of the next frame x': the momentum of the step, sum_j m_j (x'_j - x_j) / h,
    pulled toward M v_goal. Scaled like every energy here (weight (B,) relative to momentum: a
    rigid shift d of the body costs weight M |d|^2 / 2h^2); weight 0: no pull. Vertical motion
    is left to gravity and the ground (a goal along y would hold a body up)."""
    M = masses.sum(-1)
    s = (weight.to(masses.dtype) / (M * H**2)).sqrt()  # (B,)
    c = s[:, None] * masses
    t = s[:, None] * ((masses[..., None] * x).sum(1) + H * M[:, None] * goal.to(x.dtype))
    return c, t




def solve_global(bodies: Bodies, y: torch.Tensor, bones: torch.Tensor, ground: torch.Tensor, ranged: torch.Tensor,
                 kin: torch.Tensor, cfg: PhysicsConfig, com: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
    """The global step: the minimiser of the quadratic with every projection fixed (DROP Eq. 4),
    by the body's factor. y, ground, ranged, kin: (B, 22, 3); bones: (B, 21, 3). com: `com_pull`'s
    (c, t): its rank-one term c c^T on the horizontal axes is solved with the same factor by the
    Sherman-Morrison formula, so the factor stays the body's whatever the goal."""
    m = bodies.masses[..., None] / H**2
    rhs = m * (y + cfg.contact * ground + cfg.range_of_motion * ranged + bodies.kinematic[:, None, None] * kin)
    rhs = rhs + _incidence(y.dtype).T @ (_bone_weights(bodies.masses, cfg)[..., None] * bones)
    if com is None:
        return torch.cholesky_solve(rhs, bodies.factor)
    c, t = com
    u = torch.cholesky_solve(rhs + c[..., None] * horizontal(t)[:, None], bodies.factor)
    z = torch.cholesky_solve(c[..., None], bodies.factor)  # (B, 22, 1) A^-1 c
    alpha = (c[..., None] * u).sum(1) / (1.0 + (c[..., None] * z).sum(1))  # (B, 3)
    return u - z * horizontal(alpha)[:, None]


def energies(bodies: Bodies, x: torch.Tensor, y: torch.Tensor, it: torch.Tensor, cands: Candidates,
             cfg: PhysicsConfig, shift: torch.Tensor | None = None, env: Environment = FLAT,
             com: tuple[torch.Tensor, torch.Tensor] | None = None) -> dict[str, torch.Tensor]:
    """Each term of the energy the step minimises, at the solved frame `it` (B, 22, 3) after x with
    inertial target y, in joules (B,): momentum 1/(2h^2) |it - y|^2_M, and each constraint's
    weight/2 times its squared distance to its projection (what `eval physics` plots, DROP Fig. 4)."""
    m = bodies.masses[..., None] / H**2

    def term(w, target):  # w: a weight, or one per body (B,)
        return 0.5 * w * (m * (it - target) ** 2).sum((-1, -2))

    d = it[:, BONES[:, 1]] - it[:, BONES[:, 0]] - project_bones(it, bodies.rest)
    out = {"momentum": term(1.0, y),
           "rigidity": 0.5 * (_bone_weights(bodies.masses, cfg)[..., None] * d ** 2).sum((-1, -2)),
           "contact": term(cfg.contact, project_ground(it, x, env, bodies.contact_height, bodies.friction)),
           "kinematic": term(bodies.kinematic, project_prior(it, cands.joints.to(it.dtype), bodies.masses)[0])}
    if shift is not None:  # the range of motion's move (range_shift), as the step applies it
        out["range_of_motion"] = term(cfg.range_of_motion, it + shift)
    if com is not None:
        c, t = com
        out["com_velocity"] = 0.5 * (horizontal((c[..., None] * it).sum(1) - t) ** 2).sum(-1)
    return out


def step(bodies: Bodies, x: torch.Tensor, v: torch.Tensor, cands: Candidates, forces: torch.Tensor | None = None,
         cfg: PhysicsConfig | None = None, rom=None, env: Environment = FLAT, trace: list | None = None,
         pose: tuple[torch.Tensor, torch.Tensor] | None = None,
         goal: tuple[torch.Tensor, torch.Tensor] | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One frame (DROP Algorithm 1 without the correction): joints x (B, 22, 3) m and velocities
    v (B, 22, 3) m/s at t, the motion model's candidate next frames, external forces (B, 22, 3) N
    held over the frame, the range of motion (None: that energy holds everywhere), the ground and
    obstacles. Starts from the inertial target, then `iterations` local/global rounds. Returns x_{t+1},
    v_{t+1} = (x_{t+1} - x_t) / h and the index (B,) of the candidate the kinematic energy pulled
    toward last (its rotations give the body its twist). trace: a list the step's `energies` are
    appended to. pose: the rotations (root (B, 3, 3), local (B, 21, 3, 3)) whose FK x is, which the
    range of motion reads (None: no range of motion this step). goal: goal velocities (B, 3) m/s and
    the weight (B,) of the centre-of-mass velocity energy toward them (`com_pull`; 0: none)."""
    cfg = cfg or PhysicsConfig()
    x, v, cj = x.to(torch.float64), v.to(torch.float64), cands.joints.to(torch.float64)
    forces = None if forces is None else forces.to(torch.float64)
    y = inertial_target(x, v, forces, bodies.masses, cfg)
    com = None if goal is None or not bool((goal[1] > 0).any()) else com_pull(bodies.masses, x, *goal)
    # from the inertial target: an energy whose constraint holds projects the iterate onto itself,
    # which pulls toward the start until the iterations converge, so the start must be neutral
    # (from the nearest candidate, a body with no prior energy still followed the prior)
    # the range of motion moves each iterate by what moves the frame the step starts from into
    # range (its rotations are known): a joint past its limit is pulled back from the next frame
    # on. Posing each iterate instead (pose_from_particles, 4 ms a call) took 27 % of a physics
    # segment's time for 8 avatars, and 1 avatar fell from 139 to 29 frames/s
    it, k = y, None
    shift = None if rom is None or cfg.range_of_motion == 0 or pose is None else range_shift(x, *pose, bodies.offsets, rom)
    if shift is not None:  # joint limits are internal: they turn limbs, never move or spin the body
        shift = shift - rigid_part(shift, x, bodies.masses)
    for _ in range(cfg.iterations):
        kin, k = project_prior(it, cj, bodies.masses)
        ranged = it if shift is None else it + shift
        ground = project_ground(it, x, env, bodies.contact_height, bodies.friction)
        it = solve_global(bodies, y, project_bones(it, bodies.rest), ground, ranged, kin, cfg, com)
    if trace is not None:
        trace.append(energies(bodies, x, y, it, cands, cfg, shift, env, com))
    if cfg.contact > 0:  # the ground as a hard constraint at the end (as position-based dynamics
        it = project_ground(it, x, env, bodies.contact_height, bodies.friction)  # does): the energy alone left toes 7 cm under it
    return it, (it - x) / H, k


def _tree_levels() -> list[tuple]:
    """Per depth of the tree: its joints and their parents, those among them with one child (and
    the child), and those with several (the pelvis, the upper spine) with their children."""
    depth = [0] * NUM_JOINTS
    for j in range(1, NUM_JOINTS):
        depth[j] = depth[PARENTS[j]] + 1
    kids = [[c for c in range(NUM_JOINTS) if PARENTS[c] == j] for j in range(NUM_JOINTS)]
    out = []
    for d in range(max(depth) + 1):
        joints = [j for j in range(NUM_JOINTS) if depth[j] == d]
        one = [j for j in joints if len(kids[j]) == 1]
        several = [j for j in joints if len(kids[j]) > 1]
        out.append((torch.tensor(joints), torch.tensor([PARENTS[j] for j in joints]), torch.tensor(one),
                    torch.tensor([kids[j][0] for j in one]), [(j, torch.tensor(kids[j])) for j in several]))
    return out


_TREE = _tree_levels()


def pose_from_particles(x: torch.Tensor, sample_root: torch.Tensor, sample_local: torch.Tensor,
                        offsets: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The one body of solved particles x (B, 22, 3) (DROP §7): each joint's rotation is the
    chosen sample's (root (B, 3, 3), local (B, 21, 3, 3)) turned by the swing that lays its bones
    along the solved ones: the smallest rotation for a joint with one child (so the sample's twist
    about the bone stays), the best fit (Kabsch) for the pelvis and the upper spine, which carry
    several; a leaf (head, wrists, feet) keeps the sample's local rotation. Joints of one depth are
    solved together, parents first. Returns the root position (the solved pelvis), root rotation,
    local rotations and FK joints on `offsets`."""
    dt = x.dtype
    B = len(x)
    off = offsets.to(dt).expand(B, NUM_JOINTS, 3)
    sample_root, sample_local = sample_root.to(dt), sample_local.to(dt)
    G = torch.empty(B, NUM_JOINTS, 3, 3, dtype=dt)
    for j, parents, o, c, several in _TREE:
        # each joint's frame as the sample has it, carried by its parent's new rotation
        if int(j[0]) == 0:
            G[:, 0] = sample_root
        else:
            G[:, j] = G[:, parents] @ sample_local[:, j - 1]
        if len(o):
            src = (G[:, o] @ off[:, c, :, None])[..., 0]  # the bone the sample's frame lays
            G[:, o] = rot.rotation_between(src, x[:, c] - x[:, o]) @ G[:, o]
        for k, kids in several:
            src = torch.einsum("bij,bkj->bki", G[:, k], off[:, kids])
            G[:, k] = rot.kabsch(src, x[:, kids] - x[:, k:k + 1]) @ G[:, k]
    local = G[:, PARENTS[1:]].transpose(-1, -2) @ G[:, 1:]
    J, _ = forward_kinematics(x[:, 0], G[:, 0], local, off)
    return x[:, 0], G[:, 0], local, J
