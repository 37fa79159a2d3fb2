"""The avatar registry (`Crowd`) and PRIMAL's Algorithm 1 for many bodies in one batched pass.

The registry is the only thing that changes an avatar: the server and the CLI call its methods.
One segment per step (for the avatars whose queue of frames ran out):
  1 canonicalize the initial state (a SegmentBatch snapshot of the avatars)
  2-3 the sampler (runtime/sampler.py): impulses and steering impulses in the velocities the
    network is conditioned on, reverse diffusion with optional gradient guidance, adaptors
  then the post-processing stages (runtime/stages.py) chosen by the config, ending in one body
  4 back to world, queue the 15 new frames.
A command (impulse, push, goal) takes effect at the next frame: the avatar's queued frames are
dropped and its next segment starts from the frame it is showing now.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import torch

from ..body import rotations as rot
from ..body.skeleton import JOINT_INDEX, JOINT_NAMES, SHAPE_DIM, forward_kinematics, rest_offsets, rest_positions
from ..body.motion_state import (FPS, SLICES, STATE_DIM, Transform, apply_transform, canonical_transform, pack,
                                 horizontal, velocities_of)
from ..model.checkpoint import Motor
from ..physics import simulate as physics
from ..physics.environment import (OBSTACLE_CLEARANCE, FLAT, MAX_BOXES, MAX_TILT_SECONDS, Box, Environment, Ground, GroundMotion,
                                   aim_round, slide_out_of_boxes, way_ahead)
from ..physics.solver import COLLISION_RADIUS, PhysicsConfig, prepare as prepare_bodies
from ..model.persona import trajectory_of
from .guidance import goal_trajectory
from .processing import PAST, continuous_past, nearest_candidate, physical_faults
from .sampler import BatchSwitch, Sampler, _subset
from .stage_graph import run_traced_stages
from .stages import DEFAULT_STAGES, PhysicsJob, SegmentBatch, StageContext, check_stages, run_stages


def _joints(*names: str) -> list[int]:
    return [JOINT_INDEX[n] for n in names]


@dataclass(frozen=True)
class ImpulsePreset:
    joints: list[int]
    velocity: tuple[float, float, float]  # body frame (X left, Y up, Z forward), Table A1's units
    # the body's horizontal momentum is taken away with the push (every joint's velocity loses the
    # body's mean horizontal velocity): a kick, flip or roll starts from a planted stance
    stance: bool = False


# PRIMAL supplementary Table A1, body-centric (X left, Y up, Z forward). The table's velocities
# are per-frame displacements (PRIMAL trains on them, use_metric_velocity=false): x 30 fps = m/s.
# Retuned at that scale on a base that learnt DeepMimic's clips (eval impulses; docs/deepmimic.md):
# the kicks raise the foot as well, the roll dives with the upper trunk, and the acrobatics start
# from a stance: from a walking state the push alone read as a stride (failed kicks began at
# 1.2 m/s, successful ones at 0.1 m/s)
IMPULSE_PRESETS: dict[str, ImpulsePreset] = {
    "left_kick": ImpulsePreset(_joints("left_knee", "left_ankle", "left_foot"), (0.0, 0.5, 0.5), stance=True),
    "right_kick": ImpulsePreset(_joints("right_knee", "right_ankle", "right_foot"), (0.0, 0.5, 0.5), stance=True),
    "forward_run": ImpulsePreset(_joints("pelvis", "neck", "left_shoulder", "right_shoulder"), (0.0, 0.0, 1.0)),
    "back_flip": ImpulsePreset(_joints("head"), (0.0, 0.0, -1.0), stance=True),
    "forward_roll": ImpulsePreset(_joints("head", "neck", "spine3", "left_shoulder", "right_shoulder", "left_elbow",
                                          "right_elbow"), (0.0, -0.5, 0.5), stance=True),
}
IMPULSE_SCALE = 30.0
MAX_FORCE = 5000.0  # N: a force command above this is a mistake (a 400 N s push over one frame is 12,000 N: use an impulse)
MAX_BALLS = 8  # balls an avatar's simulation keeps (the oldest goes)
# seconds after an external effect (a force's end, a push, a throw, a spring's release) during
# which a body in physics mode is compliant, not calm (PhysicsJob.calm), and DROP's soft correction
# runs when it is on: unperturbed, the root-wrench metric reads like
# real motion's (eval physics), and 8 avatars corrected at every frame kept 27 frames/s each
# (39 corrected after effects only)
SETTLE = 2.0
BALL_FLIGHT = 1.0  # seconds a thrown ball may fly before it hits: the correction runs that much longer
log = logging.getLogger("avatar_motor.runtime")


@dataclass
class RuntimeConfig:
    # denoising steps per segment; 0: the model's own (8 for a DDPM base; a few-step model's
    # checkpoint names its default, and it samples in 1, 2 or 4)
    steps: int = 0
    # a persona model's text guidance (classifier-free, against the same conditions without the
    # text): 1 = as trained; above 1 the persona reads stronger, at one more batched pass for the
    # avatars that have one
    persona_scale: float = 1.0
    # a persona model's trajectory condition for a steered avatar (guidance.goal_trajectory): the
    # path the root is asked to take reaches the goal's velocity with this half-life (s), and is
    # followed with classifier-free guidance against the same conditions without it (1 = as
    # trained, one more batched pass above 1). Asked for the controller's slow 0.25-s start, a
    # standing body given a goal often kept standing; at once, the path is kept better. Guidance
    # keeps it better still but the character reads less while steered (persona card)
    trajectory_halflife: float = 0.01
    trajectory_scale: float = 1.0
    # post-processing stages by name, in order (runtime/stages.py); a body stage (leg_ik or fk)
    # always ends the list, so every frame that leaves the runtime is one body
    stages: tuple[str, ...] = DEFAULT_STAGES
    pin_feet: bool = True  # leg_ik holds a planted foot where it stood the frame before
    inertia_halflife: float = 0.2  # 0.1 measured jerkier at the joins and more skating
    smooth_sigma: float = 1.25  # temporal low-pass of each segment, frames (0 = off); our addition
    still_sigma: float = 3.0  # the low-pass of a nearly still body (speed-adaptive, One-Euro-like)
    # for bodies with a facing goal, foot locking also undoes the yaw they make on both planted
    # feet (their turning is turn_toward's, in single support). Measured on eval control (45 x 3 s,
    # seeds 0/1): ASR over unguided +0.013/+0.020 -> +0.009/+0.016, facing error 0.084 -> 0.096.
    # For every body it also cut the unguided ASR (realism 0.015 -> 0.010) but made idling
    # livelier than the data (alive 0.51 -> 0.58, real 0.38), so it is for steered bodies only:
    # those with a facing goal or a reaching target (eval reach, 1,686-step adaptor: ASR 0.106 -> 0.081,
    # distance 0.045 -> 0.048 m; near its target a reaching body twisted in place on both feet)
    # or an action label (its skating is in the first second, the turn from a foreign state into
    # the action: eval actions, 45 x 5 labels x 3 s, one adaptor: ASR 0.057 -> 0.043 at scale 1,
    # 0.082 -> 0.065 at CFG 2; R-precision 0.871 -> 0.840 and 0.884 -> 0.871)
    lock_yaw: bool = True
    fuse_velocity: float = 3.0  # weight of the predicted velocities in the joint locations (0 = off); our addition
    # speed and direction control. Default: steering impulses (ours), which the network turns into
    # steps; measured on eval control (16 states): velocity error 0.57 vs 1.33 m/s, facing error
    # 0.18 vs 1.00, ASR 0.055 vs 0.20 for gradient guidance (move 50, path 40, facing 0.2)
    steer_impulse: float = 1.5  # the body's initial velocity moved by this x (goal - current), horizontally
    turn_impulse: float = 20.0  # initial yaw rate (rad/s) = this x the angle to the facing goal
    # while the body still turns toward its facing goal, the steering velocity turns with it by
    # this fraction of the remaining angle (0 = straight at the goal, which this model side-steps;
    # 1 = walk where the body faces and curve round): people turn into a new direction. Measured on
    # eval control (45 x 3 s): 0 -> velocity error 0.748, facing 0.341; 0.5 -> 0.648, 0.277; 1 -> 0.827, 0.273
    steer_with_body: float = 0.5
    # the facing error the network leaves at a segment's end is turned out of the segment (our
    # root adjustment, processing.turn_toward), at most turn_rate rad/s in any frame (0 = off); errors within
    # turn_tolerance rad are left to the network. Measured on eval control (45 x 3 s), off -> pi/0.1:
    # velocity error 0.648 -> 0.515 m/s, facing error 0.277 -> 0.085, ASR +0.003 -> +0.014 over
    # unguided; rate 2 without tolerance: 0.512, 0.053, +0.018; 1.5 with 0.05: 0.516, 0.071, +0.019
    turn_rate: float = math.pi
    turn_tolerance: float = 0.1
    # a reaching avatar farther than this (m) from its target is given a facing goal toward it
    # (0 = never), so it goes there facing forward instead of side-stepping or backing. Measured on
    # eval reach (45 x 8 targets x 2 s, a 1,686-step adaptor): 0 -> 0.5: minimal pelvis distance
    # 0.081 -> 0.045 m, ASR 0.091 -> 0.106
    face_target_beyond: float = 0.5
    # a reaching avatar nearer than this (m) to its target, without a velocity goal of its own, is
    # given one that walks it onto the target and stops it there (0 = never): (target - pelvis) /
    # arrive_time, through the steering impulse, as a car's "arrive" behaviour slows toward its goal
    arrive_within: float = 0.5
    arrive_time: float = 0.5
    # an avatar not in physics mode whose velocity goal would take its body into an obstacle within
    # this many seconds is given the goal's part along the wall only (none into it; 0 = never): it
    # stops at a wall it walks at instead of treading on the spot against it (its frames are slid
    # out of boxes either way, environment.slide_out_of_boxes), and walks along one it meets at an angle
    wall_lookahead: float = 0.4
    # such an avatar within OBSTACLE_CLEARANCE of an obstacle draws this many candidate segments (in
    # the same batch) and is shown the one the walls move least (with a goal or a target: plus its
    # distance from where it is asked to be), so that the model's own motion turns from a wall
    # rather than being pushed along it. Seeds 0-4 (docs/physics.md): foot skating at a wall
    # head-on / turned 30 degrees, frames slid only 0.110 / 0.175; with both 0.030 / 0.036
    wall_candidates: int = 4
    # a reaching avatar whose straight way to its target runs into an obstacle is aimed round it:
    # the shortest way that keeps route_clearance m from every box (environment.route), followed
    # by heading for its point route_lookahead m ahead (aim_round; clearance 0 = straight at the
    # target, and the walls stop it). Shipped family, a wall 3 m wide between the body and its
    # target 4 m ahead, seeds 0-2 (docs/physics.md): reached in 2.3-2.8 s; straight at it, never
    route_clearance: float = 0.5
    route_lookahead: float = 3.0
    # an avatar not in physics mode whose velocity goal (a stick, a direction) meets an obstacle
    # higher than step_over within this many m is aimed round it as a target would be: at the first
    # point on the goal's line beyond the obstacle, the goal's speed kept (0 = never: it stops at a
    # wall it meets head-on, along_walls). Lower obstacles it steps over. Shipped family, a wall 3 m
    # wide 2 m ahead, 1.2 m/s, seeds 0-4 (docs/physics.md): past it in 2.7-4.0 s; with 0, never
    route_ahead: float = 3.0
    # m: an avatar not in physics mode whose pelvis comes within step_over_reach of the footprint of
    # an obstacle no higher than step_over is simulated while it is that near (physics mode, off
    # again once past), so that it steps over a curb or a low bar instead of taking it for a wall
    # (step_over 0 = never). Within OBSTACLE_CLEARANCE of the bar's centre circle instead, a walk
    # across a 2-m bar was simulated for 5 m and sank to a 0.60-m pelvis 2.5 m past it
    step_over: float = 0.3
    step_over_reach: float = 1.0
    # a reaching avatar's sampler draws this many candidate segments (in the same batch) and the
    # one whose pelvis ends nearest the target is shown (processing.nearest_candidate; 1 = off).
    # eval reach (45 x 8 targets x 2 s, scale 2.5), 1 -> 4: shipped adaptor 0.024 -> 0.018 m, ASR
    # 0.057 -> 0.062; a weak rebuild 0.044 -> 0.027 m (2 draws 0.033), ASR 0.031 -> 0.034
    reach_candidates: int = 4
    # likewise for an avatar with a velocity goal (and no target): the candidate ending nearest
    # where the goal's path takes its pelvis (guidance.goal_trajectory, trajectory_halflife).
    # Off: 1 -> 4 bought little on the base for 4x its rows (eval control, 45 x 3 s: velocity error
    # 0.312 -> 0.293 m/s, ASR +0.040 -> +0.045), more for the persona model (eval persona --n 16:
    # TPE 0.84 -> 0.60 m, the base's 0.54 -> 0.46)
    goal_candidates: int = 1
    # served, a batch may take this share of the time its avatars' queued frames cover before the
    # draws above (reach, goal and wall candidates, and those of a body simulated only to step over
    # a low obstacle; not physics mode's) are cut to fit it
    # (crowd.fit_draws, serve/world.rows_within; 0 = never cut): a late segment stalls the avatar,
    # and after a command's cut only a few frames are queued
    draw_budget: float = 0.7
    # guidance: gradient-descent steps in real units on the x0 estimate at every denoising step
    move_weight: float = 0.0  # PRIMAL's L_move (mean joint velocity); 50 with path 40 was our earlier default
    path_weight: float = 0.0  # our L_path (centroid travels at the goal velocity)
    facing_weight: float = 0.2  # PRIMAL's L_facing on the hips of the last frame
    eta: float = 1.0  # 1 = DDPM ancestral sampling, 0 = DDIM
    # what runs the base network: "onnxruntime" (the network exported in memory, model/onnx.py)
    # or "torch". `avatar-motor bench` times both in one run; measured on one core: 8-step segment
    # for one avatar 65 ms vs 99 ms (diffusion 47 vs 82), 16 avatars 396 vs 451 ms, reaction 50
    # vs 96 ms; eval realism reads the same on both (network outputs within 1e-4)
    backend: str = "onnxruntime"
    # the onnxruntime backend runs the network with int8 weights (model/onnx.quantize_int8) instead
    # of float32: off, as it bought no time for one avatar and little for crowds at a small cost
    # in quality (docs/onnx.md)
    int8_weights: bool = False
    # on a CPU with bfloat16 matrix units (AVX-512 BF16 or AMX; on others never) the network runs
    # in bfloat16, with the same realism (model card of the EMDM generator): batches of at least
    # this many rows under torch autocast, smaller ones with bfloat16 linear weights
    # (runtime/sampler.BatchSwitch); 0 = never. A batch with physics mode's candidates stays in
    # float32 (Sampler._denoiser)
    bfloat16_from: int = 8
    # the post-processing stages run as a TorchScript graph traced from them (stage_graph.py):
    # the same kernels on the same values, with less time spent dispatching them from Python
    trace_stages: bool = True
    # a new goal this close to the one the latest segment was made for (m/s; rad of facing) only
    # updates the controls, without cutting the queued frames: a gamepad stick's jitter must not
    # regenerate (issue #26: a 30-60 Hz goal stream froze the avatar)
    recut_velocity: float = 0.2
    recut_facing: float = 0.2
    # a few-step model's segments after an impulse preset (this many, 0 = none) are sampled by its
    # DDPM base, the teacher it was distilled from, at its 8 steps: the one-step generator loses
    # the kicks, flips and rolls its teacher makes (docs/deepmimic.md); 1.5 s covers a flip
    impulse_teacher: int = 3
    # avatars in physics mode (issue #29, DROP): the solver's energies and the candidates it draws
    physics: PhysicsConfig = field(default_factory=PhysicsConfig)


@dataclass
class AvatarState:
    id: int
    state: torch.Tensor  # (267,) world, the frame being shown
    shape: torch.Tensor  # (SHAPE_DIM,)
    queue: list = field(default_factory=list)  # generated frames not yet shown, (267,) each
    past: list = field(default_factory=list)  # the last PAST frames shown before `state`, oldest first
    v_goal: torch.Tensor | None = None  # (3,) world m/s
    route_goal: bool = True  # v_goal is aimed round obstacles (Crowd.set_goal)
    facing_along: bool = True  # facing_goal is v_goal's direction (none given): it turns with the way round
    routed_facing: torch.Tensor | None = None  # that way round's direction for the segment being made (_velocity_goal)
    facing_goal: torch.Tensor | None = None  # (3,) world unit
    pending_velocity: torch.Tensor | None = None  # (22, 3) world m/s to add at the next segment
    pending_stance: bool = False  # ... after taking away the body's horizontal momentum (ImpulsePreset.stance)
    # one adaptor steers an avatar at a time (a label or a target: the latest command replaces the
    # other): its index in the crowd's adaptors, the label's index in its labels, its strength
    adaptor: int | None = None
    label: int | None = None
    control_scale: float = 1.0  # the adaptor's strength for this avatar's label or target (CFG weight)
    target: torch.Tensor | None = None  # (2,) world x, z for a reaching adaptor
    # who the avatar is, for a persona model (model/persona.py): a description and its embedding
    persona: str | None = None
    persona_text: torch.Tensor | None = None  # (TEXT_DIM,)
    near_target: bool = False  # came within face_target_beyond of it: no facing goal until 2x that away
    teacher_segments: int = 0  # segments still to sample with the teacher (RuntimeConfig.impulse_teacher)
    epoch: int = 0  # bumped by every interruption
    # coalescing (see Crowd.cut): a cut's segment is being made; a further change waits for it
    regenerating: bool = False
    recut: bool = False  # some control changed while regenerating: cut again when it commits
    planned: tuple = ()  # the controls the latest prepared segment was made with
    gen: torch.Generator | None = None  # this avatar's own noise: seeded by (crowd seed, avatar id)
    # physics mode: the solver steps the body frame by frame, the model's samples its kinematic energy
    physics: bool = False
    frame: int = 0  # frames shown so far (timed forces are scheduled on it)
    forces: list = field(default_factory=list)  # [joint, (3,) N, first frame, end frame) timed forces
    springs: list = field(default_factory=list)  # physics.Spring: joints pulled toward points (drags)
    balls: list = field(default_factory=list)  # physics.Ball: the balls as of the last queued frame
    shown_balls: list = field(default_factory=list)  # and as of the frame shown
    ball_queue: list = field(default_factory=list)  # the balls of each queued frame (beside queue)
    # the kinematic energy's pull (22, 3) at each queued frame (beside queue; None off physics) and at the frame shown
    pull_queue: list = field(default_factory=list)
    shown_pull: torch.Tensor | None = None
    pending_balls: list = field(default_factory=list)  # thrown, entering at the next segment
    # the avatar frame until which the body is compliant and corrected (SETTLE after an external effect)
    disturbed_until: int = 0
    stepping_over: bool = False  # in physics mode for a low obstacle near it (RuntimeConfig.step_over), not by command

    @property
    def adapted(self) -> bool:
        """An adaptor steers it (set with its label or target, released with it), at a scale above 0
        (0 is the base model)."""
        return self.adaptor is not None and self.control_scale > 0

    @property
    def reaching(self) -> bool:
        """A reaching adaptor steers it."""
        return self.target is not None and self.adapted


def standing_state(shape: torch.Tensor | None = None, position=(0.0, 0.0), yaw: float = 0.0) -> torch.Tensor:
    """A neutral standing state (arms lowered, zero velocity) on the ground: an initial state that
    needs no data. yaw 0 faces +Z."""
    off = rest_offsets(shape, torch.float64)
    local = torch.eye(3, dtype=torch.float64).repeat(21, 1, 1)
    for name, angle in (("left_shoulder", -1.25), ("right_shoulder", 1.25)):
        local[JOINT_INDEX[name] - 1] = rot.euler_to_matrix(torch.tensor([0.0, 0.0, angle], dtype=torch.float64), "XYZ")
    for name, angle in (("left_elbow", 0.25), ("right_elbow", -0.25)):
        local[JOINT_INDEX[name] - 1] = rot.euler_to_matrix(torch.tensor([0.0, angle, 0.0], dtype=torch.float64), "XYZ")
    root_rot = rot.yaw_matrix(torch.tensor(float(yaw), dtype=torch.float64))
    root = rest_positions(off)[0].clone()
    root[0], root[2] = position
    J, _ = forward_kinematics(root, root_rot, local, off)
    return pack(root, root_rot, local, J, torch.zeros_like(J)).float()


def _reaching(batch: SegmentBatch, k: int) -> bool:
    """Whether avatar k of the batch is reaching: a target, and an adaptor to follow it."""
    return batch.targets[k] is not None and batch.adaptors[k] is not None


def fit_draws(counts: list[int], rows: int | None) -> list[int]:
    """Best-of-K draw counts (one per avatar, each >= 1) cut so that they sum to at most `rows`
    (None: as they are): the largest loses one draw at a time, the later avatar of a tie first,
    down to one draw each (an avatar is never left without its segment, so the sum may stay above
    `rows`). Extra draws buy a better choice, a late segment stalls the avatar: a batch that would
    take longer than the segment it makes is cut to fit (the server's budget, RuntimeConfig.draw_budget)."""
    out = list(counts)
    if rows is None:
        return out
    excess = sum(out) - rows
    while excess > 0 and out:  # no plain avatars (every one simulated): nothing to cut
        k = max(range(len(out)), key=lambda i: (out[i], i))
        if out[k] <= 1:
            break
        out[k] -= 1
        excess -= 1
    return out


def _raised(x: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
    """States x (B, 267) or (B, N, 267) moved up by h (B,) m, or for (B, N, 267) by h (B, N) m a
    frame (the root and every joint)."""
    if not bool((h != 0).any()):
        return x
    out = x.clone()
    up = h.to(x.dtype).reshape(*h.shape, *[1] * (x.dim() - h.dim()))
    r, j = SLICES["root_pos"].start, SLICES["joints"].start
    out[..., r + 1:r + 2] += up
    out[..., j + 1:j + 66:3] += up
    return out


def _slid(seg: torch.Tensor, x0: torch.Tensor, env: Environment) -> tuple[torch.Tensor, torch.Tensor]:
    """World segments (B, N, 267) that follow states x0 (B, 267), moved along the obstacles they
    walk into (environment.slide_out_of_boxes): root and joints shifted, the shift's own velocity
    added to the joints' backward differences (frame 0's from x0), so each frame stays one body
    (the rotations, and so the exported body's shape, are untouched); and how far (B,) m each
    segment was moved by its end."""
    B, N = seg.shape[:2]
    j = SLICES["joints"]
    shift = slide_out_of_boxes(seg[..., j].reshape(B, N, 22, 3), x0[:, j].reshape(B, 22, 3), COLLISION_RADIUS, env)
    moved = shift[:, -1].norm(dim=-1)
    if not bool((shift != 0).any()):
        return seg, moved
    out = seg.clone()
    out[..., SLICES["root_pos"]] += shift
    out[..., j] += shift.repeat(1, 1, 22)
    step = torch.diff(shift, dim=1, prepend=torch.zeros(B, 1, 3, dtype=shift.dtype)) * FPS
    out[..., SLICES["velocities"]] += step.repeat(1, 1, 22)
    return out, moved


def _body_to_world(a: AvatarState) -> torch.Tensor:
    """The yaw rotation from the avatar's body frame (X left, Z forward) to the world."""
    return canonical_transform(a.state[None].double()).R[0].float()


def _check_scale(scale: float) -> None:
    if not (math.isfinite(scale) and 0 <= scale <= 10):
        raise ValueError(f"adaptor scale must be in [0, 10] (0 = base model, 1 = as trained), got {scale}")


def validate_vector(v, n: int, what: str) -> torch.Tensor:
    t = torch.as_tensor(v, dtype=torch.float32).flatten()
    if t.numel() != n or not torch.isfinite(t).all():
        raise ValueError(f"{what} must be {n} finite numbers, got {v!r}")
    return t


class Crowd:
    def __init__(self, motor: Motor, config: RuntimeConfig | None = None, seed: int = 0, adaptors=None,
                 range_of_motion=None):
        """adaptors: AdaptedDenoisers on motor's (base) network, for labels or targets: a list, one,
        or None. Several may be loaded (actions, styles, reaching); each avatar is steered by at
        most one of them at a time. range_of_motion: the joint limits of physics mode
        (physics.limits; None: no limits, as without models/range-of-motion)."""
        self.motor = motor
        self.range_of_motion = range_of_motion
        self.trace: dict | None = None  # set to {} to collect each avatar's physics energies per frame
        self.environment: Environment = FLAT  # the ground and obstacles of physics mode (set_ground, add_obstacle)
        # the ground turning to environment.ground (set_ground with seconds), or None; its frames
        # are the crowd's clock: advance() calls so far (the world's frame numbers)
        self.ground_motion: GroundMotion | None = None
        self.clock = 0
        self.cfg = config or RuntimeConfig()
        check_stages(self.cfg.stages)  # a misspelt stage is named now, not at the first segment
        for name in ("persona_scale", "trajectory_scale", "trajectory_halflife", "draw_budget", "step_over", "step_over_reach"):  # likewise: not mid-serve
            v = getattr(self.cfg, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and (v > 0 if name == "trajectory_halflife" else v >= 0)):
                raise ValueError(f"runtime {name} must be a finite number {'above' if name == 'trajectory_halflife' else 'at least'} 0, got {v!r}")
        self.sampler = Sampler(motor, self.cfg, adaptors)
        self.cfg = self.sampler.cfg  # its steps resolved for this model
        self.seed = seed
        self.avatars: dict[int, AvatarState] = {}
        self._next_id = 0
        self.timings: dict[str, float] = {}
        # frames kept queued when a command cuts an avatar's queue (see _changed); a real-time
        # server sets it to cover one segment's generation, offline it is 0
        self.keep_on_cut = 0
        # the most network rows a batch may have (fit_draws cuts the best-of-K draws to it; None:
        # every draw): a real-time server sets it from how long a row takes now, offline it is None
        self.max_rows: int | None = None
        self.guard_resets = 0  # segments refused by the physical guard (see commit)

    # ------------------------------------------------------------ avatars
    def spawn(self, state: torch.Tensor | None = None, shape: torch.Tensor | None = None,
              position=(0.0, 0.0), yaw: float = 0.0) -> int:
        shape = torch.zeros(SHAPE_DIM) if shape is None else validate_vector(shape, SHAPE_DIM, "body shape")
        if state is None:
            state = standing_state(shape, position, yaw)
        state = validate_vector(state, STATE_DIM, "initial state")
        i = self._next_id
        self._next_id += 1
        self.avatars[i] = AvatarState(i, state, shape, gen=torch.Generator().manual_seed(self._noise_seed(i)))
        return i

    def _noise_seed(self, i: int) -> int:
        """Avatar i's own noise stream under the crowd's seed: a crowd and the same avatar alone agree."""
        return self.seed * 100003 + i

    def remove(self, i: int) -> None:
        self._get(i)
        del self.avatars[i]

    @property
    def adaptors(self) -> list:
        """The loaded adaptors (labels or targets), in the order given."""
        return self.sampler.adaptors

    def _adaptor_for(self, control: str, label: str | None = None) -> int:
        """The index of the first adaptor of that control (and knowing that label)."""
        for k, ad in enumerate(self.adaptors):
            if ad.cfg.control == control and (label is None or label in ad.cfg.labels):
                return k
        if control == "target":
            raise ValueError("no reaching adaptor loaded (avatar-motor adapt with configs/reach.json, then --adaptor DIR)")
        known = sorted({lb for ad in self.adaptors if ad.cfg.control == "label" for lb in ad.cfg.labels})
        if not known:
            raise ValueError("no action adaptor loaded: labels need one (avatar-motor adapt with configs/actions.json, "
                             "then --adaptor DIR)")
        raise ValueError(f"unknown label {label!r}; the loaded adaptors know {known}")

    def _get(self, i: int) -> AvatarState:
        if i not in self.avatars:
            raise KeyError(f"no avatar {i}; avatars are {sorted(self.avatars)}")
        return self.avatars[i]

    def __len__(self) -> int:
        return len(self.avatars)

    def __contains__(self, i) -> bool:
        return i in self.avatars

    def ids(self) -> list[int]:
        """The avatars' ids, ascending (= spawn order)."""
        return sorted(self.avatars)

    def state(self, i: int) -> torch.Tensor:
        """The (267,) world state avatar i shows now (not a copy: do not write to it)."""
        return self._get(i).state

    def shape(self, i: int) -> torch.Tensor:
        """Avatar i's (SHAPE_DIM,) body shape (not a copy), e.g. to export its motion on its bones."""
        return self._get(i).shape

    def goal_velocity(self, i: int) -> torch.Tensor | None:
        """Avatar i's goal velocity, (3,) world m/s, or None: lets a caller re-aim only on a real change."""
        return self._get(i).v_goal

    def needs_frames(self, min_frames: int) -> bool:
        """Whether some avatar has fewer than min_frames queued: the ones `prepare` would serve."""
        return any(len(a.queue) < min_frames for a in self.avatars.values())

    def reset(self, i: int) -> None:
        """Stand avatar i up where it is (pelvis x, z; facing +Z) with every control released (goals,
        label, target, pending impulses), from the next frame: the way back from a fall or a runaway
        push."""
        a = self._get(i)
        a.state = standing_state(a.shape, (float(a.state[0]), float(a.state[2])))
        if a.physics:  # on the ground it stands on (tilted, or turning)
            up = self.ground_at(self.clock).height_below(a.state[SLICES["joints"]][[0, 2]].double())
            a.state = _raised(a.state[None].double(), up.reshape(1)).float()[0]
        a.past, a.shown_pull = [], None
        a.v_goal = a.facing_goal = a.pending_velocity = a.adaptor = a.label = a.target = None
        a.pending_stance = False
        a.near_target = False
        a.teacher_segments = 0
        a.forces, a.springs, a.balls, a.shown_balls, a.pending_balls = [], [], [], [], []
        self.interrupt(i)

    def reseed(self, seed: int) -> None:
        """Restart every avatar's noise from `seed` as spawn seeds it (and use it for later spawns), so
        a continuation is reproducible from here: the frames shown so far are forgotten (a crowd
        spawned with the states shown now has none). Frames already queued are kept."""
        self.seed = seed
        for i, a in self.avatars.items():
            a.gen.manual_seed(self._noise_seed(i))
            a.past = []

    def interrupt(self, i: int) -> None:
        """Drop all queued frames so the next segment starts from the frame shown now; segments
        being generated for the old queue are discarded (epoch)."""
        a = self._get(i)
        self._trim(a, 0)
        a.epoch += 1
        a.regenerating, a.recut = True, False

    @staticmethod
    def _trim(a: AvatarState, n: int) -> None:
        """Keep the first n queued frames (and their balls): the next segment starts after them."""
        del a.queue[n:]
        del a.ball_queue[n:]
        del a.pull_queue[n:]
        a.balls = list(a.ball_queue[-1]) if a.ball_queue else list(a.shown_balls)

    def _changed(self, a: AvatarState) -> None:
        """A control of avatar a changed. If the queued frames no longer follow it, they are cut:
        the first `keep_on_cut` frames stay (they are shown while the new segment is made, so a
        real-time clock never stalls; 0 offline: the command shows at the next frame) and the next
        segment continues from there. While a cut's segment is being made, further changes only
        mark a recut, done when that segment commits: regeneration never runs faster than
        segments are made, so commands arriving at any rate coalesce and frames keep flowing."""
        if not self._differs(a):
            return
        if a.regenerating:
            a.recut = True
            return
        self._trim(a, self.keep_on_cut)
        a.epoch += 1
        a.regenerating = True

    def _plan(self, a: AvatarState) -> tuple:
        return (a.v_goal, a.facing_goal, (a.adaptor, a.label, a.persona), a.target, a.control_scale)

    def _differs(self, a: AvatarState) -> bool:
        """Whether a's controls differ from those its latest segment was made for beyond the
        recut tolerances (an impulse always does)."""
        if a.pending_velocity is not None or not a.planned:
            return True
        (v0, f0, label0, target0, scale0), (v, f, label, target, scale) = a.planned, self._plan(a)

        def far(p, q, tol):
            if p is None or q is None:
                return (p is None) != (q is None)
            return float((p - q).norm()) > tol

        # facing vectors are unit: their distance is about the angle between them
        return (far(v0, v, self.cfg.recut_velocity) or far(f0, f, self.cfg.recut_facing) or label0 != label
                or far(target0, target, 0.1) or scale0 != scale)

    # ------------------------------------------------------------ controls
    def set_goal(self, i: int, velocity=None, facing=None, route: bool = True) -> None:
        """velocity: world (vx, vz) m/s or None to release; facing: world (fx, fz) or None (= along
        velocity); route: aim it round an obstacle in its way (RuntimeConfig.route_ahead; off for a
        goal already aimed at a point, the serve magnet's)."""
        a = self._get(i)
        a.route_goal, a.facing_along = route, facing is None
        if velocity is None:
            a.v_goal, a.facing_goal = None, None
        else:
            v = validate_vector(velocity, 2, "goal velocity (vx, vz)")
            a.v_goal = torch.tensor([v[0], 0.0, v[1]])
            f = validate_vector(facing, 2, "facing (fx, fz)") if facing is not None else v
            n = float(f.norm())
            a.facing_goal = torch.tensor([f[0] / n, 0.0, f[1] / n]) if n > 1e-6 else None
        self._changed(a)

    def set_persona(self, i: int, description: str | None) -> None:
        """Who avatar i is, in words ("a weary old man"), or the name of a character the model was
        characterized with (`adapt persona`), for a persona model; None releases it (the model then
        moves it with no text, as its base would). The body shape is the avatar's own."""
        a = self._get(i)
        if description is None:
            a.persona, a.persona_text = None, None
        else:
            if not self.motor.net.cfg.persona:
                raise ValueError(f"model {self.motor.name!r} has no persona conditions; serve a persona model "
                                 "(models/primal-bandai-persona, built with configs/persona.json)")
            from ..model.text import embed_texts
            known = self.motor.config.get("personas", {})  # characterized ones (adapt persona): by name
            if description.strip() in known:
                a.persona_text = torch.tensor(known[description.strip()], dtype=torch.float32)
            else:
                a.persona_text = embed_texts([description])[0]
            a.persona = description.strip()
        self._changed(a)

    def set_label(self, i: int, label: str | None, scale: float | None = None) -> None:
        """Action label of the adaptor (None releases); scale 0 = base model, 1 = as trained, above 1
        guidance of that weight, against the adaptor's `guidance` (AdaptedDenoiser._negative);
        None: the adaptor's default_scale."""
        a = self._get(i)
        if label is None:
            if a.label is not None:
                a.label, a.adaptor = None, None
        else:
            k = self._adaptor_for("label", label)
            scale = self.adaptors[k].scale_for(scale)
            _check_scale(scale)
            a.adaptor, a.label, a.target = k, self.adaptors[k].cfg.labels.index(label), None
            a.control_scale = float(scale)
        self._changed(a)

    def set_target(self, i: int, position, scale: float | None = None) -> None:
        """World (x, z) target of a reaching adaptor (None releases); re-expressed in every
        segment's canonical frame, so a moving target is followed. scale as for labels: below 1
        the base model's continuity weighs more (measured: slower, less sliding)."""
        a = self._get(i)
        if position is None:
            if a.target is not None:
                a.target, a.adaptor = None, None
        else:
            k = self._adaptor_for("target")
            scale = self.adaptors[k].scale_for(scale)
            _check_scale(scale)
            a.target, a.label, a.adaptor = validate_vector(position, 2, "target (x, z)"), None, k
            a.control_scale = float(scale)
        a.near_target = False
        self._changed(a)

    def impulse(self, i: int, preset: str, scale: float = 1.0) -> None:
        """Apply a Table A1 preset (body-centric) at the next frame."""
        if preset not in IMPULSE_PRESETS:
            raise ValueError(f"unknown impulse preset {preset!r}; presets are {sorted(IMPULSE_PRESETS)}")
        if not math.isfinite(scale):
            raise ValueError("impulse scale must be finite")
        p = IMPULSE_PRESETS[preset]
        a = self._get(i)
        vw = _body_to_world(a) @ (torch.tensor(p.velocity) * IMPULSE_SCALE * scale)
        dv = torch.zeros(22, 3)
        dv[p.joints] = vw
        a.teacher_segments = self.cfg.impulse_teacher
        a.pending_stance |= p.stance  # taken from the state the segment starts at (prepare)
        self._add_velocity(a, dv)

    def push(self, i: int, joint: int | str, velocity, frame: str = "world") -> None:
        """Add a velocity (m/s) to one joint: a poke from a user. frame 'world' or 'body'."""
        a = self._get(i)
        j = self._joint(joint)
        v = validate_vector(velocity, 3, "push velocity")
        if frame == "body":
            v = _body_to_world(a) @ v
        elif frame != "world":
            raise ValueError(f"frame must be 'world' or 'body', got {frame!r}")
        dv = torch.zeros(22, 3)
        dv[j] = v
        self._add_velocity(a, dv)

    def _add_velocity(self, a: AvatarState, dv: torch.Tensor) -> None:
        a.pending_velocity = dv if a.pending_velocity is None else a.pending_velocity + dv
        if a.physics:  # a blow on the simulated body
            self._disturb(a)
        self._changed(a)

    # ------------------------------------------------------------ physics (DROP)
    def set_physics(self, i: int, on: bool) -> None:
        """Physics mode for avatar i: from the next segment its body is stepped by the solver
        (physics/), the model's samples its kinematic energy; off, the model alone again. Either
        way the motion continues from the frame shown, so toggling does not jump. Off drops its
        forces, springs and balls."""
        a = self._get(i)
        a.stepping_over = False  # the command's mode from now on (step_over may turn it on again near a low obstacle)
        if bool(on) == a.physics:
            return
        a.physics = bool(on)
        if not a.physics:
            a.forces, a.springs, a.balls, a.shown_balls, a.pending_balls = [], [], [], [], []
        self._cut(a)  # nothing hit the body: it starts calm (PhysicsJob.calm)

    def _physical(self, a: AvatarState, what: str) -> None:
        if not a.physics:
            raise ValueError(f"avatar {a.id} is not in physics mode: {what} acts only on a simulated body; "
                             "turn physics on for it first")

    def _perturbed(self, a: AvatarState, until: int | None = None) -> None:
        """Something acts on the body from outside: the queued frames no longer hold (they are cut
        like a command's) and the body is disturbed (until: see _disturb)."""
        self._disturb(a, until)
        self._cut(a)

    def _cut(self, a: AvatarState) -> None:
        """The queued frames no longer hold (physics turned on or off, the world changed), though
        nothing hit the body."""
        a.planned = ()
        self._changed(a)

    def _disturb(self, a: AvatarState, until: int | None = None) -> None:
        """An external effect on avatar a lasting to frame `until` (None: the first frame a cut
        makes anew): the body is compliant (and corrected) until SETTLE after it."""
        end = a.frame + self.keep_on_cut + 1 if until is None else until
        a.disturbed_until = max(a.disturbed_until, end + round(SETTLE * FPS))

    def _joint(self, joint) -> int:
        j = JOINT_NAMES.index(joint) if isinstance(joint, str) and joint in JOINT_NAMES else joint
        if not isinstance(j, int) or isinstance(j, bool) or not 0 <= j < 22:
            raise ValueError(f"unknown joint {joint!r}; use an index 0..21 or one of {JOINT_NAMES}")
        return j

    def apply_force(self, i: int, joint, force, seconds: float) -> None:
        """A world force (N) on one joint for `seconds`, from the next segment (physics mode)."""
        a = self._get(i)
        self._physical(a, "a force")
        f = validate_vector(force, 3, "force (N)")
        if float(f.norm()) > MAX_FORCE:
            raise ValueError(f"force of {float(f.norm()):.0f} N is above {MAX_FORCE:.0f} N")
        if not (math.isfinite(seconds) and 0 < seconds <= 10):
            raise ValueError(f"force duration must be in (0, 10] s, got {seconds}")
        first = a.frame + self.keep_on_cut + 1  # the first frame the cut makes anew
        a.forces.append((self._joint(joint), f, first, first + max(1, round(seconds * FPS))))
        self._perturbed(a, a.forces[-1][3])

    def set_spring(self, i: int, joint, target, stiffness: float = 400.0) -> None:
        """Pull a joint toward a world point (x, y, z) with a spring of `stiffness` N/m (the
        studio's drag); target None releases that joint (physics mode)."""
        a = self._get(i)
        j = self._joint(joint)
        a.springs = [sp for sp in a.springs if sp.joint != j]
        if target is not None:
            self._physical(a, "a spring")
            if not (math.isfinite(stiffness) and 0 < stiffness <= 5000):
                raise ValueError(f"spring stiffness must be in (0, 5000] N/m, got {stiffness}")
            k = float(stiffness)
            a.springs.append(physics.Spring(j, validate_vector(target, 3, "spring target (x, y, z)").double(), k,
                                            2 * math.sqrt(k * 5.0)))  # about critically damped on a 5 kg limb
        self._perturbed(a)

    def throw(self, i: int, position, velocity, mass: float = 1.0, radius: float = 0.11) -> None:
        """A ball from a world position with a world velocity (m/s), simulated with avatar i (physics
        mode): it hits the body if its path meets it. An avatar keeps its newest MAX_BALLS."""
        a = self._get(i)
        self._physical(a, "a ball")
        ball = physics.Ball(validate_vector(position, 3, "ball position").double(),
                            validate_vector(velocity, 3, "ball velocity").double(), float(mass), float(radius))
        ball.validate()
        if float(ball.velocity.norm()) > 60:
            raise ValueError(f"ball speed {float(ball.velocity.norm()):.0f} m/s is above 60 m/s")
        a.pending_balls.append(ball)  # it enters where the next segment starts (after the cut)
        self._perturbed(a, a.frame + round(BALL_FLIGHT * FPS))  # it may fly that long before it hits

    def set_ground(self, tilt=(0.0, 0.0), pivot=(0.0, 0.0), seconds: float = 0.0) -> None:
        """Tilt the ground (degrees about world X, then Z) about the point pivot (x, z) on the floor;
        (0, 0) is the flat floor. seconds > 0: a tilting platform, turning from the ground shown
        now to that one at a constant rate over that time. It acts on the avatars in physics mode
        (they are resampled from the frame shown); the others walk the flat floor as the model
        knows it."""
        if not (isinstance(seconds, (int, float)) and math.isfinite(seconds) and 0 <= seconds <= MAX_TILT_SECONDS):
            raise ValueError(f"ground seconds must be a number in [0, {MAX_TILT_SECONDS:g}], got {seconds!r}")
        end = Ground(tuple(tilt), tuple(pivot))
        start, frames = self.ground_at(self.clock), round(seconds * FPS)
        if start.flat:  # the floor is the same about any pivot: the platform turns about the new one
            start = Ground(start.tilt, end.pivot)
        before = self.turning()
        self.ground_motion = GroundMotion(start, end, self.clock, frames) if frames > 0 and end != start else None
        # (the same end another way to it: the simulated avatars' queued frames met the old way)
        self.set_environment(Environment(end, self.environment.boxes), resample=self.ground_motion != before)

    def turning(self) -> GroundMotion | None:
        """The ground's motion while it is turning now (set_ground's seconds), else None."""
        m = self.ground_motion
        return None if m is None or m.over(self.clock) else m

    def ground_at(self, t: int) -> Ground:
        """The ground at world frame t (the crowd's clock): turning, or the environment's."""
        m = self.ground_motion
        return self.environment.ground if m is None else m.at(t)

    def add_obstacle(self, centre, size, yaw: float = 0.0) -> int:
        """A static box standing on the floor at centre (x, z), of size (x, y, z) m, turned by yaw
        degrees; avatars in physics mode run into it (a low one trips a foot), the others meet it
        as a wall and slide along it (environment.slide_out_of_boxes). Returns its index."""
        if len(self.environment.boxes) >= MAX_BOXES:
            raise ValueError(f"this world holds at most {MAX_BOXES} obstacles; remove one first")
        self.set_environment(Environment(self.environment.ground,
                                          self.environment.boxes + (Box(tuple(centre), tuple(size), float(yaw)),)))
        return len(self.environment.boxes) - 1

    def remove_obstacle(self, index: int | None = None) -> None:
        """Remove obstacle `index` (None: all of them)."""
        boxes = self.environment.boxes
        if index is None:
            boxes = ()
        elif isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < len(boxes):
            raise ValueError(f"no obstacle {index!r}; this world has {len(boxes)} (indices 0..{len(boxes) - 1})")
        else:
            boxes = boxes[:index] + boxes[index + 1:]
        self.set_environment(Environment(self.environment.ground, boxes))

    def set_environment(self, env: Environment, resample: bool = False) -> None:
        """The ground (for avatars in physics mode) and the obstacles (for every avatar; see
        set_ground, add_obstacle). resample: the avatars in physics mode are resampled from the
        frame shown even if env is the one they had (the ground's motion to it changed)."""
        if env == self.environment and not resample:
            return
        self.environment = env
        j = SLICES["joints"]
        for a in self.avatars.values():
            if a.physics:  # their queued frames met the old world
                self._cut(a)
            elif a.queue and env.boxes:  # the model's alone, if its queued frames walk into a box now
                J = torch.stack(a.queue).double()[:, j].reshape(1, -1, 22, 3)
                if bool(slide_out_of_boxes(J, a.state.double()[j].reshape(1, 22, 3), COLLISION_RADIUS, env).any()):
                    self._cut(a)

    def balls(self, i: int) -> list:
        """The balls avatar i's simulation holds at the frame shown (physics.Ball, world)."""
        return self._get(i).shown_balls

    # ------------------------------------------------------------ generation
    def advance(self) -> tuple[dict[int, torch.Tensor], list[int]]:
        """Show the next queued frame of every avatar that has one; the others hold their pose (a
        real-time clock does not wait for generation). Returns the frame each avatar shows and the
        ids of those that had none ready (stalled)."""
        shown, stalled = {}, []
        for i, a in self.avatars.items():
            if a.queue:
                a.past = (a.past + [a.state])[-PAST:]
                a.state = a.queue.pop(0)
                if a.ball_queue:
                    a.shown_balls = a.ball_queue.pop(0)
                if a.pull_queue:
                    a.shown_pull = a.pull_queue.pop(0)
                a.frame += 1
                a.forces = [f for f in a.forces if f[3] > a.frame]
            else:
                stalled.append(i)
            shown[i] = a.state
        self.clock += 1
        return shown, stalled

    def next_frames(self) -> dict[int, torch.Tensor]:
        """Advance every avatar by one frame (generating a segment for those that need one) and
        return the frame each now shows."""
        self.refill(1)
        return self.advance()[0]

    def step_segment(self) -> dict[int, torch.Tensor]:
        """Generate one whole segment for every avatar from its current state (offline use)."""
        for a in self.avatars.values():
            self._trim(a, 0)
        for _ in range(3):  # again for an avatar the physical guard stood up (commit): its queue is empty
            if not self.refill(1):
                break
        out = {}
        for a in self.avatars.values():
            if not a.queue:  # a model that keeps failing the guard: the avatar holds its (standing) state
                a.queue.append(a.state)
            out[a.id] = torch.stack(a.queue)
            a.past = (a.past + [a.state] + a.queue[:-1])[-PAST:]
            a.state = a.queue[-1]
            a.shown_balls = list(a.balls)
            a.shown_pull = a.pull_queue[-1] if a.pull_queue else None
            a.frame += len(a.queue)
            self._trim(a, 0)
        return out

    def refill(self, min_frames: int) -> int:
        """Generate one segment (in one batch) for every avatar with fewer than `min_frames` queued
        frames, continuing from the last queued frame. Returns how many avatars were served."""
        batch = self.prepare(min_frames)
        if batch is None:
            return 0
        self.commit(batch, self.compute(batch))
        return len(batch)

    def prepare(self, min_frames: int, only: set[int] | None = None) -> SegmentBatch | None:
        """Snapshot what to generate (call under the owner's lock in threaded use); only: just
        these avatars (the others wait), e.g. to find which avatar of a failing batch fails it."""
        avs = [a for a in self.avatars.values() if len(a.queue) < min_frames and (only is None or a.id in only)]
        if not avs:
            return None
        self._step_over(avs)
        N = self.motor.net.cfg.frames
        grounds = None  # the ground of each frame of the segment, while it turns (set_ground's seconds)
        if self.ground_motion is not None and any(a.physics for a in avs):
            first = min(len(a.queue) for a in avs if a.physics)
            if not self.ground_motion.over(self.clock + first + 1):
                # one ground per frame for every simulated body of the batch: those whose new
                # segments start later (longer queues) wait for the next batch
                avs = [a for a in avs if not a.physics or len(a.queue) == first]
                grounds = tuple(self.ground_at(self.clock + first + 1 + i) for i in range(N))
        x0 = torch.stack([a.queue[-1] if a.queue else a.state for a in avs]).double()
        # the frames before x0 where the avatar has that many (the join's smoothing and blending read
        # them; processing.continuous_past checks they lead into x0)
        past = torch.zeros(len(avs), PAST, STATE_DIM, dtype=torch.float64)
        has_past = torch.zeros(len(avs), dtype=torch.bool)
        for k, a in enumerate(avs):
            before = (a.past + [a.state] + a.queue)[:-1][-PAST:]
            if len(before) == PAST:
                past[k], has_past[k] = torch.stack(before).double(), True
        dv = torch.zeros(len(avs), 22, 3, dtype=torch.float64)  # impulses: world velocities added to x0
        impulse = torch.zeros(len(avs), dtype=torch.bool)
        for k, a in enumerate(avs):
            if a.pending_velocity is not None:  # only set with a cut: this segment starts at the cut
                dv[k] = a.pending_velocity.double()
                if a.pending_stance:
                    moving = horizontal(velocities_of(x0[k]).mean(0))
                    dv[k] -= moving
                a.pending_velocity, a.pending_stance = None, False
                impulse[k] = True
            a.planned = self._plan(a)
        jobs = []
        plain_near = self.environment.plain_near(x0[:, SLICES["joints"]][:, [0, 2]], OBSTACLE_CLEARANCE)
        if grounds is not None:  # a turning ground is not the open floor a calm body is held on
            plain_near[:] = False
        aims = [self._aim(a) for a in avs]
        v_goals = [self._velocity_goal(a, *aim) for a, aim in zip(avs, aims)]
        facing_goals = [self._facing_goal(a, m) for a, (m, _) in zip(avs, aims)]
        for n_a, a in enumerate(avs):
            if not a.physics:
                jobs.append(None)
                continue
            first = a.frame + len(a.queue) + 1  # the avatar frame of this segment's first new frame
            forces = torch.zeros(N, 22, 3, dtype=torch.float64)
            for j, f, start, end in a.forces:
                lo, hi = max(start, first) - first, min(end, first + N) - first
                if hi > lo:
                    forces[lo:hi, j] += f.double()
            # thrown balls stay pending until a segment with them commits (a cut one would lose them)
            disturbed = bool(a.springs) or first <= a.disturbed_until  # a spring while it pulls
            jobs.append(PhysicsJob(forces, list(a.springs), (a.balls + a.pending_balls)[-MAX_BALLS:], list(a.pending_balls),
                                   disturbed, a.pull_queue[-1] if a.queue else a.shown_pull,
                                   # (an impulse queued before physics was turned on disturbed nothing)
                                   calm=not disturbed and not bool(impulse[n_a]) and bool(plain_near[n_a]),
                                   stepping=a.stepping_over and not disturbed and not bool(impulse[n_a])))
        return SegmentBatch(
            avatars=[a.id for a in avs], epochs=[a.epoch for a in avs], x0=x0, past=past, has_past=has_past,
            impulse_velocity=dv, impulse=impulse,
            shapes=torch.stack([a.shape for a in avs]), gens=[a.gen for a in avs], labels=[a.label for a in avs],
            control_scales=[a.control_scale for a in avs], targets=[m for m, _ in aims],
            adaptors=[a.adaptor if a.adapted else None for a in avs],
            v_goal=v_goals, facing_goal=facing_goals, physics=jobs, personas=[a.persona_text for a in avs],
            teacher=[a.teacher_segments > 0 for a in avs], max_rows=self.max_rows, grounds=grounds)

    def _step_over(self, avs: list[AvatarState]) -> None:
        """Physics mode, from the segment about to be made, for the avatars not in it that are near
        an obstacle no higher than RuntimeConfig.step_over (the model alone cannot lift a foot over
        it: the frames would be slid along it as along a wall), and off again for those it was
        turned on for once they are past and nothing acts on the body (no force, spring or ball
        just thrown, and settled after the last; its balls then go, as with the command). No cut:
        the queued frames are shown first, as they would be anyway, and the next segment continues
        from them."""
        low = tuple(b for b in self.environment.boxes if b.size[1] <= self.cfg.step_over)
        if not low and not any(a.stepping_over for a in avs):
            return
        xz = torch.stack([self._pelvis_xz(a) for a in avs]).double()
        away = ~Environment(boxes=low).over_footprint(xz, self.cfg.step_over_reach)
        for a, far in zip(avs, away.tolist()):
            if not far and not a.physics:
                a.physics = a.stepping_over = True
            elif (far and a.stepping_over and a.frame + len(a.queue) + 1 > a.disturbed_until
                  and not (a.springs or a.pending_balls or a.forces)):
                a.physics = a.stepping_over = False
                a.balls, a.shown_balls = [], []  # as with the command (set_physics)

    @staticmethod
    def _pelvis_xz(a: AvatarState) -> torch.Tensor:
        """Horizontal (x, z) of the pelvis of the state the avatar's next segment starts from."""
        x = a.queue[-1] if a.queue else a.state
        return x[SLICES["joints"]][[0, 2]]

    def _aim(self, a: AvatarState) -> tuple[torch.Tensor | None, bool]:
        """Where a reaching avatar's next segment is aimed (its target, or round an obstacle in the
        way: RuntimeConfig.route_clearance) and whether that is the target itself (None, True: no target)."""
        if a.target is None:
            return None, True
        aim, direct = aim_round(self._pelvis_xz(a), a.target, self.environment, self.cfg.route_clearance,
                                 self.cfg.route_lookahead)
        return (a.target, True) if direct else (aim.to(a.target.dtype), False)

    def _velocity_goal(self, a: AvatarState, aim: torch.Tensor | None = None, direct: bool = True) -> torch.Tensor | None:
        """The avatar's velocity goal, or, for a reaching avatar without one, the arrival at its
        target once it is within arrive_within and in the open way (`aim`, `direct`: _aim's)."""
        a.routed_facing = None
        if a.v_goal is not None or not a.reaching or self.cfg.arrive_within <= 0 or not direct:
            routed = self._round_walls(a, a.v_goal)
            a.routed_facing = None if routed is a.v_goal or not a.facing_along else routed / routed.norm()
            return self._along_walls(a, routed)
        d = (a.target if aim is None else aim) - self._pelvis_xz(a)
        if float(d.norm()) > self.cfg.arrive_within:
            return None
        return self._along_walls(a, torch.tensor([float(d[0]), 0.0, float(d[1])]) / self.cfg.arrive_time)

    def _round_walls(self, a: AvatarState, v: torch.Tensor | None) -> torch.Tensor | None:
        """Velocity goal v (3,) turned, at its own speed, toward the way round an obstacle its line
        meets within route_ahead m (RuntimeConfig; environment.way_ahead, aim_round), or v."""
        if v is None or a.physics or not a.route_goal or self.cfg.route_ahead <= 0 or self.cfg.route_clearance <= 0:
            return v
        walls = Environment(self.environment.ground, tuple(b for b in self.environment.boxes if b.size[1] > self.cfg.step_over))
        vxz = v.double()[[0, 2]]
        speed = float(vxz.norm())
        if not walls.boxes or speed < 1e-6:
            return v
        s = self._pelvis_xz(a).double()
        goal = way_ahead(s, vxz, walls, self.cfg.route_clearance, self.cfg.route_ahead, self.cfg.route_clearance / 2)
        if goal is None:
            return v
        aim, direct = aim_round(s, goal, walls, self.cfg.route_clearance, self.cfg.route_lookahead)
        w = aim - s
        if direct or float(w.norm()) < 1e-6:
            return v
        w = w / w.norm() * speed
        return torch.tensor([float(w[0]), float(v[1]), float(w[1])], dtype=v.dtype)

    def _along_walls(self, a: AvatarState, v: torch.Tensor | None) -> torch.Tensor | None:
        """Velocity goal v (3,) less its part into the obstacle the body would meet going at it for
        wall_lookahead s (RuntimeConfig): the way the wall would push that body (slide_out_of_boxes)
        is the wall's normal. Physics mode's bodies run into walls themselves."""
        if v is None or a.physics or not self.environment.boxes or self.cfg.wall_lookahead <= 0:
            return v
        x = a.queue[-1] if a.queue else a.state
        J = x.double()[SLICES["joints"]].reshape(1, 22, 3)
        ahead = J + self.cfg.wall_lookahead * v.double()
        push = slide_out_of_boxes(ahead[:, None], J, COLLISION_RADIUS, self.environment)[0, 0]
        if float(push.norm()) < 1e-6:
            return v
        n = push / push.norm()
        into = float(v.double() @ n)
        return v if into >= 0 else (v.double() - into * n).to(v.dtype)

    def _facing_goal(self, a: AvatarState, aim: torch.Tensor | None = None) -> torch.Tensor | None:
        """The avatar's facing goal, or, for a reaching avatar without one, the way to its target
        (`aim`, _aim's: the way round an obstacle) while it is farther than face_target_beyond."""
        if a.facing_goal is not None or not a.reaching or self.cfg.face_target_beyond <= 0:
            return a.facing_goal if a.routed_facing is None else a.routed_facing
        d = (a.target if aim is None else aim) - self._pelvis_xz(a)
        n = float(d.norm())
        # hysteresis: a body standing near the threshold would otherwise switch its facing goal
        # on and off from segment to segment; a target that moves off again is faced again
        a.near_target = n <= self.cfg.face_target_beyond * (2.0 if a.near_target else 1.0)
        return None if a.near_target else torch.tensor([d[0] / n, 0.0, d[1] / n])

    @torch.inference_mode()
    def compute(self, batch: SegmentBatch, cancelled=None) -> torch.Tensor:
        """Algorithm 1 for a prepared batch; touches no avatar (safe outside the lock).
        cancelled: see Sampler.sample."""
        import time

        t0 = time.perf_counter()
        offsets = rest_offsets(batch.shapes, torch.float64)
        # 1 canonicalize
        tf = canonical_transform(batch.x0)
        Rt = tf.R.transpose(-1, -2)
        x0c = apply_transform(batch.x0[:, None], Rt, -(Rt @ tf.t[..., None])[..., 0])[:, 0]
        pastc = apply_transform(batch.past, Rt, -(Rt @ tf.t[..., None])[..., 0])
        phys = [k for k, job in enumerate(batch.physics) if job is not None]
        plain = [k for k, job in enumerate(batch.physics) if job is None]
        # the model knows a flat floor at y = 0: a simulated body on a tilted ground is sampled as
        # if that floor lay at the ground's height under its pelvis (and its candidates raised back)
        floor = torch.zeros(len(batch), dtype=torch.float64)
        ground = batch.grounds[0] if batch.grounds else self.environment.ground
        if phys and not ground.flat:
            floor[phys] = ground.height_below(batch.x0[phys][:, SLICES["joints"]][:, [0, 2]].double())
            x0c, pastc = _raised(x0c, -floor), _raised(pastc, -floor)
        has_past = continuous_past(x0c, pastc, batch.has_past)
        t1 = time.perf_counter()
        # 2 condition embedding, 3 reverse diffusion with guidance: one segment per avatar, and for
        # an avatar in physics mode K candidates instead (a calm one: candidates_calm), all in one batch
        counts = self._candidate_counts(batch, phys)
        # and a reaching avatar reach_candidates of them (best-of-K: the one ending nearest is shown)
        reach = [self.cfg.reach_candidates if _reaching(batch, k)
                 else self.cfg.goal_candidates if batch.v_goal[k] is not None else 1 for k in plain]
        if self.environment.boxes and plain:
            pelvis = batch.x0[plain][:, SLICES["joints"]][:, [0, 2]]
            walls = ~Environment(boxes=self.environment.boxes).plain_near(pelvis, OBSTACLE_CLEARANCE)
            reach = [max(c, self.cfg.wall_candidates) if bool(w) else c for c, w in zip(reach, walls)]
        if batch.max_rows is not None:  # the server's budget: fewer draws rather than a late segment
            # (a body stepping over a bar, nothing acting on it, among them: 8 candidates made its
            # segments 8x as long as a plain avatar's and stalled a served crowd near a bar)
            cut = [n for n, k in enumerate(phys) if batch.physics[k].stepping]
            fixed = sum(counts) - sum(counts[n] for n in cut)
            both = fit_draws(reach + [counts[n] for n in cut], batch.max_rows - fixed)
            reach = both[:len(reach)]
            for n, c in zip(cut, both[len(reach):]):
                counts[n] = c
        plain_rows = [k for k, c in zip(plain, reach) for _ in range(c)]
        rows = torch.tensor(plain_rows + [k for k, c in zip(phys, counts) for _ in range(c)], dtype=torch.long)
        every = len(rows) == len(batch) and not phys
        sub = batch if every else _subset(batch, rows)
        seg_all = self.sampler.sample(sub, x0c if every else x0c[rows],
                                      tf if every else Transform(tf.R[rows], tf.t[rows]), cancelled)
        t2 = time.perf_counter()
        seg_w = torch.empty(len(batch), seg_all.shape[1], STATE_DIM)
        lengths, ball_frames = [seg_all.shape[1]] * len(batch), [[] for _ in range(len(batch))]
        pulls = [None] * len(batch)
        if plain:
            # test-time processing, ending in one body, in float32: in the canonical frame every value
            # is within metres of the origin, and float64 made it 1.3-1.6x slower (bench, one run)
            p = torch.tensor(plain_rows)
            sub_p = batch if every else _subset(batch, p)
            seg = self._stages(StageContext.of(self.cfg, x0c[p].float(), offsets[p].float(), sub_p, Rt[p].float(),
                                               pastc[p].float(), has_past[p]),
                               seg_all[:len(plain_rows)].float())
            # 4 back to world
            seg = apply_transform(seg.double(), tf.R[p], tf.t[p])
            moved = None
            if self.environment.boxes:  # before the choice: a goal's candidate is judged where the wall lets it go
                seg, moved = _slid(seg, batch.x0[p].double(), self.environment)
            if len(plain_rows) > len(plain):
                seg = self._choose_nearest(batch, plain, reach, seg, moved)
            seg_w[torch.tensor(plain)] = seg.float()
        t3 = time.perf_counter()
        if phys:
            seg_w[torch.tensor(phys)], lengths_p, balls_p, pulls_p = self._simulate(batch, phys, counts, seg_all[len(plain_rows):],
                                                                                     x0c, tf, offsets, floor, pastc, has_past)
            for n, k in enumerate(phys):
                lengths[k], ball_frames[k], pulls[k] = lengths_p[n], balls_p[n], pulls_p[n]
        t4 = time.perf_counter()
        batch.lengths, batch.ball_frames, batch.pulls = lengths, ball_frames, pulls
        self.timings = {"canonicalize": t1 - t0, "diffusion": t2 - t1, "post": t3 - t2, "physics": t4 - t3,
                        "total": t4 - t0, "batch": len(batch),
                        "rows": len(rows)}
        return seg_w

    @torch.inference_mode()
    def warm(self) -> None:
        """Trace the post-processing graphs this runtime can use (stage_graph.py: with and without
        a facing goal, with the frames shown before and without, as physics mode's candidates)
        and run each twice (TorchScript optimizes a graph at its second run), so that no avatar's
        segment waits for it: unwarmed, the first segment of each kind took 0.15-0.2 s more and the
        second 0.06 s more. Once per process and runtime config; the server does it at start.
        Also the network's bfloat16 forms: autocast's kernels are set up at their first call (60
        ms), the small batches' traced graph is optimized at its second."""
        net, cfg = self.sampler.net, self.motor.net.cfg
        if isinstance(net, BatchSwitch):
            for B in (net.rows, 1, 1):
                net(torch.zeros(B, dtype=torch.long), torch.zeros(B, cfg.frames, STATE_DIM), torch.zeros(B, STATE_DIM),
                    *([torch.zeros(B, cfg.latent)] if cfg.latent else []))
        if not self.cfg.trace_stages:
            return
        x0 = standing_state().float()[None]
        seg = x0[:, None].expand(1, cfg.frames, STATE_DIM)
        yes, no = torch.ones(1, dtype=torch.bool), torch.zeros(1, dtype=torch.bool)
        for facing in (False, True):
            for past in (x0[:, None].expand(1, PAST, STATE_DIM), None):
                ctx = StageContext(x0, rest_offsets(None, torch.float32)[None], no, torch.zeros(1), yes if facing else no,
                                   yes, no, yes, past, None if past is None else yes, any_facing=facing)
                for _ in range(2):
                    self._stages(ctx, seg)

    def _stages(self, ctx: StageContext, seg: torch.Tensor) -> torch.Tensor:
        """The post-processing stages, as a traced graph or in Python (the same values)."""
        if self.cfg.trace_stages:
            return run_traced_stages(self.cfg, ctx, seg)
        return run_stages(self.cfg, ctx, seg)

    def _choose_nearest(self, batch: SegmentBatch, plain: list[int], counts: list[int], seg: torch.Tensor,
                        moved: torch.Tensor | None = None) -> torch.Tensor:
        """Of the plain avatars' world segments (counts[n] rows each, in turn), each one's: its only
        row, or the candidate that ends nearest where it is asked to be: a reaching avatar's target,
        else where its velocity goal's path takes the pelvis from x0 (neither: anywhere), plus how
        far the walls moved it (moved (rows,) m, _slid; None: nothing moved)."""
        per = torch.tensor(counts)
        start = per.cumsum(0) - per
        chosen = start.clone()
        many = [n for n, c in enumerate(counts) if c > 1]
        K = max(counts)
        idx = start[many][:, None] + torch.arange(K)[None] % per[many][:, None]
        wanted = torch.full((len(many), 2), float("nan"), dtype=torch.float64)
        reaching = torch.tensor([_reaching(batch, plain[n]) for n in many])
        goal = torch.tensor([batch.v_goal[plain[n]] is not None and not reaching[m] for m, n in enumerate(many)])
        for m, n in enumerate(many):
            if reaching[m]:
                wanted[m] = batch.targets[plain[n]].double()
        if goal.any():
            g = torch.tensor([plain[n] for m, n in enumerate(many) if goal[m]])
            x0 = batch.x0[g].double()
            v = torch.stack([batch.v_goal[int(k)].double() for k in g])
            path = goal_trajectory(x0, v, None, seg.shape[1], self.cfg.trajectory_halflife)[..., :2]  # (G, N, 2)
            pelvis0 = x0[:, SLICES["joints"]].reshape(len(g), 22, 3)[:, 0, [0, 2]]
            wanted[goal] = pelvis0 + path[:, -1] - trajectory_of(x0[:, None])[:, 0, :2]
        penalty = None if moved is None else moved[idx]
        chosen[many] = idx[torch.arange(len(many)), nearest_candidate(seg[idx], wanted, penalty)]
        return seg[chosen]

    def _candidate_counts(self, batch: SegmentBatch, phys: list[int]) -> list[int]:
        """How many candidate segments each avatar in physics mode samples: PhysicsConfig.candidates,
        a calm one candidates_calm (PhysicsJob.calm)."""
        cfg = self.cfg.physics
        return [cfg.candidates_calm if batch.physics[k].calm else cfg.candidates for k in phys]

    def _simulate(self, batch: SegmentBatch, phys: list[int], counts: list[int], cands_c: torch.Tensor, x0c: torch.Tensor,
                  tf: Transform, offsets: torch.Tensor, floor: torch.Tensor, pastc: torch.Tensor, has_past: torch.Tensor):
        """Physics mode: the candidate segments of each such avatar (counts[n] rows each, in turn;
        canonical, as the network made them, on a floor at height `floor` (B,)) as bodies in the
        world (a body with fewer than the most candidates repeats its own), then the solver
        through the segment (physics/simulate) in the world's environment, a goal velocity pulling
        on the centre of mass (PhysicsConfig.com_velocity), the kinematic pull carried from the
        frame before where the body continues it (has_past, with the frames before it pastc)."""
        N, per = cands_c.shape[1], torch.tensor(counts)
        idx = torch.tensor(phys).repeat_interleave(per)
        jobs = [batch.physics[k] for k in phys]
        calm = torch.tensor([job.calm for job in jobs])
        # each candidate processed as a plain avatar's segment is (its feet locked and above the
        # ground, one body): the prior pulls toward what the runtime shows, not the network's raw
        # frames, whose feet slid and sank (8 unperturbed rollouts: ASR 0.15, toes 7.5 cm deep).
        # A calm body's candidates, which it follows stiffly, are joined to the frames shown before
        # them as a plain avatar's are (64 rollouts, seeds 0-3: jitter 1.36 -> 1.27); a compliant
        # body's continuity is the solver's momentum (with the simulated past its jerk in a
        # segment's middle rose: 63-78 against 49-63 m/s^3, 32 rollouts)
        ctx = StageContext.of(self.cfg, x0c[idx].float(), offsets[idx].float(), _subset(batch, idx),
                              tf.R[idx].transpose(-1, -2).float(), pastc[idx].float(),
                              (calm & has_past[phys]).repeat_interleave(per))
        cands = self._stages(ctx, cands_c.float()).double()
        cands = _raised(apply_transform(cands, tf.R[idx], tf.t[idx]), floor[idx])
        if batch.grounds:  # a turning ground: each frame's candidates ride it, as the body's feet do
            xz = batch.x0[phys][:, SLICES["joints"]][:, [0, 2]].double()  # (the pelvis where the segment starts)
            rise = torch.stack([g.height_below(xz) for g in batch.grounds], 1)  # (P, N)
            cands = _raised(cands, (rise - rise[:, :1]).repeat_interleave(per, 0))
        K, start = max(counts), per.cumsum(0) - per
        cands = cands[start[:, None] + torch.arange(K)[None] % per[:, None]]  # (P, K, N, 267)
        p = torch.tensor(phys)
        x0 = batch.x0[p].clone()
        # a push (impulse velocity) is a blow on the particles: their velocities change at once
        x0[:, SLICES["velocities"]] += batch.impulse_velocity[p].reshape(len(phys), 66)
        bodies = prepare_bodies(offsets[p], self.cfg.physics, calm)
        trace = [] if self.trace is not None else None
        pull = torch.zeros(len(phys), 22, 3, dtype=torch.float64)
        for n, (k, job) in enumerate(zip(phys, jobs)):
            # (not after an external effect: a pushed body is far from candidates that no longer
            # describe it, and carried on, that pull flung bodies up to 4 m into the air)
            if job.pull is not None and bool(has_past[k]) and not job.disturbed:
                pull[n] = job.pull.double()
        frames, balls, _, lengths, pulls = physics.segment(bodies, x0, cands, self.cfg.physics, self.range_of_motion,
                                                           torch.stack([j.forces for j in jobs]), [j.springs for j in jobs],
                                                           [j.balls for j in jobs], trace, [j.disturbed for j in jobs],
                                                           self.environment, self._goals([batch.v_goal[k] for k in phys]), pull,
                                                           torch.tensor([not (j.calm or j.disturbed) for j in jobs]), batch.grounds)
        if trace is not None:  # per avatar, the energies of the frames it keeps
            for n, k in enumerate(phys):
                self.trace.setdefault(batch.avatars[k], []).extend(
                    {term: float(e[n]) for term, e in frame.items()} for frame in trace[:lengths[n]])
        return frames.float(), lengths, balls, pulls.float()

    def _goals(self, v_goals: list) -> tuple[torch.Tensor, torch.Tensor] | None:
        """Goal velocities (B, 3) and the centre-of-mass energy's weight (B,) for the solver."""
        w = self.cfg.physics.com_velocity
        if w <= 0 or all(v is None for v in v_goals):
            return None
        goal = torch.stack([torch.zeros(3, dtype=torch.float64) if v is None else v.double() for v in v_goals])
        return goal, torch.tensor([0.0 if v is None else w for v in v_goals], dtype=torch.float64)

    def stale(self, batch: SegmentBatch) -> bool:
        """Every avatar of the batch was cut or removed since it was prepared: its result would be
        dropped (read without the lock: a stale answer only costs one more network call)."""
        return all((a := self.avatars.get(i)) is None or a.epoch != e for i, e in zip(batch.avatars, batch.epochs))

    def abandon(self, batch: SegmentBatch) -> None:
        """A prepared batch that will not be committed (it failed or was cancelled): the impulses
        it took go back to their avatars, so the next segment still applies them."""
        for k, (i, e) in enumerate(zip(batch.avatars, batch.epochs)):
            a = self.avatars.get(i)
            if a is not None and a.epoch == e and bool(batch.impulse[k]):
                dv = batch.impulse_velocity[k].float()
                a.pending_velocity = dv if a.pending_velocity is None else a.pending_velocity + dv

    def commit(self, batch: SegmentBatch, seg_w: torch.Tensor) -> None:
        """Append generated frames, unless a command cut the avatar's queue meanwhile; a change
        that waited for this segment cuts now. A segment that is not a physical body
        (processing.physical_faults) is never queued: that avatar is stood up where it is, with a
        log line."""
        seg_d = seg_w.double()
        floor = None  # a simulated body stands on the ground, tilted (and turning) or not
        phys = [k for k, job in enumerate(batch.physics) if job is not None]
        if phys and not (batch.grounds is None and self.environment.ground.flat):
            floor = torch.zeros(seg_d.shape[:2], dtype=torch.float64)
            pelvis = seg_d[phys][:, :, SLICES["joints"]][..., [0, 2]]  # (P, N, 2)
            for i in range(seg_d.shape[1]):
                g = batch.grounds[i] if batch.grounds else self.environment.ground
                floor[phys, i] = g.height_below(pelvis[:, i])
        faults = physical_faults(batch.x0, seg_d, rest_offsets(batch.shapes, torch.float64), floor)
        for k, (i, epoch) in enumerate(zip(batch.avatars, batch.epochs)):
            a = self.avatars.get(i)
            if a is not None and a.epoch == epoch:
                if faults[k]:
                    self.guard_resets += 1
                    if self.guard_resets in (1, 10, 100) or self.guard_resets % 1000 == 0:  # a broken model: not a line per segment
                        log.warning("avatar %d: the generated motion is not a physical body (%s): reset, standing where it "
                                    "was (%d such resets so far; is the checkpoint broken?)", i, faults[k], self.guard_resets)
                    self.reset(i)
                    continue
                n = batch.lengths[k] if batch.lengths else len(seg_w[k])
                a.queue.extend(seg_w[k, :n].unbind(0))
                if batch.teacher and batch.teacher[k]:
                    a.teacher_segments -= 1
                frames_balls = batch.ball_frames[k] if batch.ball_frames and batch.ball_frames[k] else [[]] * n
                a.ball_queue.extend(list(b) for b in frames_balls[:n])
                pulls = batch.pulls[k] if batch.pulls else None
                a.pull_queue.extend([None] * n if pulls is None else list(pulls[:n].unbind(0)))
                a.balls = list(a.ball_queue[-1]) if a.physics else []
                if batch.physics[k] is not None:
                    a.pending_balls = [b for b in a.pending_balls if not any(b is t for t in batch.physics[k].thrown)]
                a.regenerating = False
                if a.recut:
                    a.recut = False
                    self._changed(a)

class Avatar:
    """One body: a Crowd of one with a friendlier interface."""

    def __init__(self, motor: Motor, config: RuntimeConfig | None = None, seed: int = 0,
                 state: torch.Tensor | None = None, shape: torch.Tensor | None = None):
        self.crowd = Crowd(motor, config, seed)
        self.id = self.crowd.spawn(state, shape)

    @property
    def state(self) -> torch.Tensor:
        return self.crowd.state(self.id)

    def next_frame(self) -> torch.Tensor:
        return self.crowd.next_frames()[self.id]

    def segment(self) -> torch.Tensor:
        return self.crowd.step_segment()[self.id]

    def rollout(self, frames: int) -> torch.Tensor:
        return torch.stack([self.next_frame() for _ in range(frames)])

    def set_goal(self, velocity=None, facing=None) -> None:
        self.crowd.set_goal(self.id, velocity, facing)

    def impulse(self, preset: str, scale: float = 1.0) -> None:
        self.crowd.impulse(self.id, preset, scale)

    def push(self, joint, velocity, frame: str = "world") -> None:
        self.crowd.push(self.id, joint, velocity, frame)
