"""Post-processing as named, ordered stages (DESIGN §5). Each stage maps the generated segment
(canonical frame) to a new one, reading the batch's controls and the runtime config and changing
no avatar (turn_toward leaves the yaw it added in the context, for lock_feet not to undo it);
the work is done by the pure functions of processing.py. `RuntimeConfig.stages` picks them by name
and order. Whatever is chosen, the segment ends as one
body: when the last stage chosen is not a body stage, `fk` is appended, so the joint locations
that leave the runtime are FK of the rotations that leave it."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch

from ..body.motion_state import FPS, SLICES
from .processing import (fuse_velocities, inertialize, lock_feet, smooth_segment, snap_to_ground, solve_body,
                         turn_toward)


@dataclass
class PhysicsJob:
    """What acts on an avatar in physics mode over its segment, from its first new frame."""
    forces: torch.Tensor  # (N, 22, 3) world N at each frame (timed forces and pushes held)
    springs: list  # physics.Spring
    balls: list  # physics.Ball, as of the segment's initial state
    thrown: list  # those of them thrown since the last segment (pending until this one commits)
    disturbed: bool = True  # an external effect is recent: the soft correction runs (Crowd.SETTLE)
    pull: torch.Tensor | None = None  # (22, 3) the kinematic energy's pull at the initial state (simulate.segment)
    # nothing acts on the body and nothing is near it (Crowd.prepare): the solver's calm weight and
    # candidates (PhysicsConfig.kinematic_calm, candidates_calm)
    calm: bool = False
    # simulated only to step over a low obstacle (RuntimeConfig.step_over), nothing acting on it:
    # served over the row budget, its candidates are cut with the plain avatars' draws
    stepping: bool = False


@dataclass
class SegmentBatch:
    """One segment to generate for each of B avatars: a snapshot taken under the owner's lock,
    so generation can run outside it. World frame unless said otherwise."""
    avatars: list[int]
    epochs: list[int]  # each avatar's interruption count at the snapshot (stale results are dropped)
    x0: torch.Tensor  # (B, 267) float64, the frame each segment continues from
    past: torch.Tensor  # (B, PAST, 267) float64, the frames shown before x0, oldest first
    has_past: torch.Tensor  # (B,) bool: the avatar has that many (not just spawned, reset or stood up)
    impulse_velocity: torch.Tensor  # (B, 22, 3) world m/s added to x0's velocities for the network
    impulse: torch.Tensor  # (B,) bool: an impulse is applied at this segment
    shapes: torch.Tensor  # (B, SHAPE_DIM)
    gens: list  # each avatar's torch.Generator
    labels: list  # label index in the steering adaptor's labels, or None
    control_scales: list[float]
    targets: list  # world (x, z) tensors or None
    adaptors: list  # index of the adaptor (Sampler.adaptors) that steers each avatar, or None
    v_goal: list  # world (3,) m/s or None
    facing_goal: list  # world unit (3,) or None
    physics: list  # a PhysicsJob for an avatar in physics mode, else None
    personas: list | None = None  # each avatar's persona text embedding (TEXT_DIM,) or None
    teacher: list | None = None  # bool each: sampled by a few-step model's DDPM base (after an impulse preset)
    max_rows: int | None = None  # the most rows the batch may have (Crowd.max_rows, crowd.fit_draws)
    grounds: tuple | None = None  # physics rows: the ground of each frame while it turns (Crowd.ground_motion), else None
    # what compute() found, for commit: how many frames of each row to queue (a physics segment
    # stops early to resample after a hit), and the balls of each frame [row][frame][ball]
    lengths: list | None = None
    ball_frames: list | None = None
    pulls: list | None = None  # physics rows: the kinematic pull at each frame (n, 22, 3), else None

    def __len__(self) -> int:
        return len(self.avatars)

    @property
    def adapted(self) -> list[bool]:
        """An adaptor steers the avatar."""
        return [k is not None for k in self.adaptors]

    @property
    def steered(self) -> torch.Tensor:
        """(B,) bool: a goal, a label or a target steers the avatar."""
        return torch.tensor([v is not None or f is not None or ad
                             for v, f, ad in zip(self.v_goal, self.facing_goal, self.adapted)])


@dataclass
class StageContext:
    """What the stages read besides the segment, in the segment's canonical frame: tensors, and
    Python values that do not depend on the batch's contents beyond `any_facing`, so that the
    stages can run as one graph (runtime/stage_graph.py). `of` makes it from a SegmentBatch."""
    x0: torch.Tensor  # (B, 267) canonical initial state
    offsets: torch.Tensor  # (B, 22, 3) each body's bones
    steered: torch.Tensor  # (B,) bool: a goal, a label or a target steers the body
    facing: torch.Tensor  # (B,) canonical yaw of the facing goal (0 without one)
    has_facing: torch.Tensor  # (B,) bool: the body has a facing goal
    lock_where: torch.Tensor  # (B,) bool: lock_feet moves the body
    lock_yaw: torch.Tensor  # (B,) bool: lock_feet also undoes a yaw on both planted feet
    match_velocity: torch.Tensor  # (B,) bool: inertialize matches velocities (no impulse at this segment)
    # (B, PAST, 267) the frames shown before x0, canonical, and (B,) where they lead into x0
    # (processing.continuous_past); None: no past (each stage then extrapolates x0)
    past: torch.Tensor | None = None
    has_past: torch.Tensor | None = None
    any_facing: bool = True  # some body has a facing goal (False: turn_toward is skipped)
    turned: torch.Tensor | None = None  # (B, N) yaw added on purpose by turn_toward

    @classmethod
    def of(cls, cfg, x0: torch.Tensor, offsets: torch.Tensor, batch: SegmentBatch, Rt: torch.Tensor,
           past: torch.Tensor | None = None, has_past: torch.Tensor | None = None) -> "StageContext":
        """The context of a batch's segments; Rt (B, 3, 3) world -> canonical rotation."""
        has_facing = torch.tensor([f is not None for f in batch.facing_goal])
        facing = torch.zeros(len(batch), dtype=x0.dtype)
        if bool(has_facing.any()):
            F = torch.stack([torch.zeros(3) if f is None else f.float() for f in batch.facing_goal]).to(Rt.dtype)
            g = (Rt @ F[..., None])[..., 0]
            facing = torch.where(has_facing, torch.atan2(g[:, 0], g[:, 2]), torch.zeros(1, dtype=g.dtype)).to(x0.dtype)
        # not under gradient speed guidance: with it this model glides rather than steps, and
        # locking its feet would stop the avatar (measured: 0.03 m instead of 1.8 m in 4 s)
        gliding = cfg.move_weight > 0 or cfg.path_weight > 0
        return cls(x0, offsets, batch.steered, facing, has_facing,
                   lock_where=torch.tensor([v is None or not gliding for v in batch.v_goal]),
                   lock_yaw=torch.tensor([cfg.lock_yaw and (f is not None or ad)
                                          for f, ad in zip(batch.facing_goal, batch.adapted)]),
                   match_velocity=~batch.impulse, past=past, has_past=has_past, any_facing=bool(has_facing.any()))


def _fuse(cfg, ctx: StageContext, seg):
    return fuse_velocities(ctx.x0, seg, cfg.fuse_velocity)


def _turn(cfg, ctx: StageContext, seg):
    if cfg.turn_rate <= 0 or not ctx.any_facing:
        return seg
    seg, ctx.turned = turn_toward(ctx.x0, seg, ctx.facing, cfg.turn_rate, cfg.turn_tolerance, ctx.has_facing)
    return seg


def _lock(cfg, ctx: StageContext, seg):
    return lock_feet(ctx.x0, seg, where=ctx.lock_where, yaw=ctx.lock_yaw, turned=ctx.turned)


def max_smoothing_width(cfg) -> float:
    """The widest smoothing_widths can be."""
    return max(cfg.smooth_sigma, cfg.still_sigma)


def smoothing_widths(cfg, x0: torch.Tensor, seg: torch.Tensor) -> torch.Tensor:
    """Per-body smoothing width: smooth_sigma when moving, up to still_sigma for a body that is
    nearly still (mean joint speed below 0.1 m/s, ramping up to 0.5), like a One-Euro filter: the
    network's residual wobble is what a still body shows most, and real idling is very still."""
    J = torch.cat((x0[:, None], seg), 1)[..., SLICES["joints"]].reshape(seg.shape[0], -1, 22, 3)
    speed = ((J[:, 1:] - J[:, :-1]).norm(dim=-1).mean((1, 2)) * FPS)
    still = ((0.5 - speed) / 0.4).clamp(0.0, 1.0)
    return cfg.smooth_sigma + max(0.0, cfg.still_sigma - cfg.smooth_sigma) * still


def _smooth(cfg, ctx: StageContext, seg):
    if cfg.smooth_sigma <= 0:
        return seg
    return smooth_segment(ctx.x0, seg, smoothing_widths(cfg, ctx.x0, seg), ctx.past, ctx.has_past,
                          max_smoothing_width(cfg))


def _snap(cfg, ctx: StageContext, seg):
    return snap_to_ground(seg)


def _inertialize(cfg, ctx: StageContext, seg):
    before = None if ctx.past is None else ctx.past[:, -1]
    # a body's own turn carries across the join unless it is turning toward a facing goal
    return inertialize(ctx.x0, seg, cfg.inertia_halflife, match_velocity=ctx.match_velocity, before=before,
                       has_before=ctx.has_past, turn_root=~ctx.has_facing)


def _fk(cfg, ctx: StageContext, seg):
    return solve_body(ctx.x0, seg, ctx.offsets)


def _free_body(cfg, ctx: StageContext, seg):
    # the network's rotations pose a free body more naturally than its joint locations do, so the
    # root-motion stages work on that body; a steered body keeps the predicted locations, as its
    # rotations lag the steering and their feet glide (model card, "One body")
    # (every row is solved and the steered ones keep theirs: no row selection depending on the
    # batch, so the stages are one graph)
    return torch.where(ctx.steered[:, None, None], seg, solve_body(ctx.x0, seg, ctx.offsets))


def _leg_ik(cfg, ctx: StageContext, seg):
    # a steered body's legs step where the processed feet step; a free body's legs are already
    # its rotations' and are only kept above the ground
    return solve_body(ctx.x0, seg, ctx.offsets, follow=ctx.steered.to(seg.dtype), pin=cfg.pin_feet)


Stage = Callable[[object, StageContext, torch.Tensor], torch.Tensor]
STAGES: dict[str, Stage] = {
    "fuse_velocities": _fuse,  # joint locations agreeing with the predicted velocities
    "turn_toward": _turn,  # root adjustment toward a facing goal
    "lock_feet": _lock,  # planted feet do not slide: root motion from the feet
    "smooth": _smooth,  # speed-adaptive temporal low-pass
    "snap": _snap,  # lowest joint of the segment on the ground
    "inertialize": _inertialize,  # the join blended with decaying springs
    "free_body": _free_body,  # unsteered bodies take the pose of their rotations
    # ONE body: joint locations := FK of the rotations on the pelvis location ...
    "fk": _fk,  # ... and nothing else
    "leg_ik": _leg_ik,  # ... legs bent by IK: onto the processed feet (steered), above the ground (all)
}
BODY_STAGES = ("fk", "leg_ik")
DEFAULT_STAGES = ("fuse_velocities", "free_body", "turn_toward", "lock_feet", "smooth", "snap", "inertialize", "leg_ik")


def check_stages(names) -> tuple[str, ...]:
    names = tuple(names)
    unknown = [n for n in names if n not in STAGES]
    if unknown:
        raise ValueError(f"unknown post-processing stage(s) {unknown}; stages are {list(STAGES)}")
    return names


def run_stages(cfg, ctx: StageContext, seg: torch.Tensor) -> torch.Tensor:
    """The stages of cfg.stages in order, then `fk` unless a body stage came last."""
    names = check_stages(cfg.stages)
    if not names or names[-1] not in BODY_STAGES:
        names = names + ("fk",)
    for name in names:
        seg = STAGES[name](cfg, ctx, seg)
    return seg
