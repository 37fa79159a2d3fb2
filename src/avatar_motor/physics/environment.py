"""What the simulated bodies stand on and run into (DROP §8: a tilted platform, obstacles that trip
a foot): the ground, a plane that may be tilted about a pivot, and static boxes standing on the
flat floor (y = 0). Both act through the solver's contact energy: a joint's collision sphere that
enters one is projected back to its surface with static friction (it stays where it was when it
touched; on the ground, a compliant body's joint slips past Coulomb's limit). No new weight, no
change to the system matrix (solver.py): the contact projection is only a different set.

A foot that meets a box's side is held at the point where it touched until the motion model's
pull lifts it above the top: so a box across the path trips a walking body the way DROP's fixed
heel does, and a box low enough is stepped over. Balls bounce off the ground and the boxes
(simulate.py). A body the motion model moves alone (not in physics mode) meets a box as a wall:
it is moved out of it as one piece and slides along it (slide_out_of_boxes). Pure functions on
batched tensors; the world (runtime Crowd) holds one Environment for every avatar."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

MAX_TILT = 30.0  # degrees: steeper ground is a wall, which the motion model has never seen
MAX_BOXES = 32  # obstacles a world holds
BOX_SIZE = (0.02, 3.0)  # m: smallest and largest side of an obstacle
# m: a body this near an obstacle (or anywhere on a tilted ground) may meet it within a segment:
# the rules for a body in the open (the runtime's calm, stiff pull; the solver's flight rule) do not
# hold there (a stiff pull drags a caught foot through the box's face, a flight rule drops a
# stepping foot into it)
OBSTACLE_CLEARANCE = 1.5


def _finite(v, n: int, what: str, lo: float, hi: float) -> tuple:
    try:
        t = tuple(float(x) for x in v)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be {n} numbers, got {v!r}") from None
    if len(t) != n or not all(math.isfinite(x) and lo <= x <= hi for x in t):
        raise ValueError(f"{what} must be {n} finite numbers in [{lo:g}, {hi:g}], got {v!r}")
    return t


@dataclass(frozen=True)
class Ground:
    """The ground plane: the floor y = 0 turned by `tilt` (degrees about the world X axis, then about
    Z) about the point `pivot` (x, z) on it. Untilted, it is the floor everything else assumes."""
    tilt: tuple = (0.0, 0.0)
    pivot: tuple = (0.0, 0.0)

    def __post_init__(self):
        object.__setattr__(self, "tilt", _finite(self.tilt, 2, "ground tilt (degrees about x, about z)", -MAX_TILT, MAX_TILT))
        object.__setattr__(self, "pivot", _finite(self.pivot, 2, "ground pivot (x, z m)", -1000, 1000))

    @property
    def flat(self) -> bool:
        return self.tilt == (0.0, 0.0)

    def rotation(self, dtype=torch.float64) -> torch.Tensor:
        """(3, 3) the floor's turn: R_z(tilt z) R_x(tilt x)."""
        ax, az = (math.radians(a) for a in self.tilt)
        cx, sx, cz, sz = math.cos(ax), math.sin(ax), math.cos(az), math.sin(az)
        Rx = torch.tensor([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]], dtype=dtype)
        Rz = torch.tensor([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]], dtype=dtype)
        return Rz @ Rx

    def normal(self, dtype=torch.float64) -> torch.Tensor:
        """(3,) the plane's unit normal, up."""
        return self.rotation(dtype)[:, 1]

    def origin(self, dtype=torch.float64) -> torch.Tensor:
        """(3,) a point of the plane: the pivot on the floor."""
        return torch.tensor([self.pivot[0], 0.0, self.pivot[1]], dtype=dtype)

    def height(self, p: torch.Tensor) -> torch.Tensor:
        """(...,) signed distance of points p (..., 3) above the plane."""
        return ((p - self.origin(p.dtype)) * self.normal(p.dtype)).sum(-1)

    def height_below(self, xz: torch.Tensor) -> torch.Tensor:
        """(...,) the plane's y under world points (..., 2) x, z (where a vertical line meets it)."""
        n, o = self.normal(xz.dtype), self.origin(xz.dtype)
        return o[1] - (n[0] * (xz[..., 0] - o[0]) + n[2] * (xz[..., 1] - o[2])) / n[1]


MAX_TILT_SECONDS = 60.0  # the longest a ground takes to turn to a new tilt


@dataclass(frozen=True)
class GroundMotion:
    """A tilting platform (DROP Fig. 1): the ground turning from `start` to `end` (tilt and pivot
    each linearly, at a constant rate) over `frames` frames from world frame `frame` on; before
    it the start, after it the end."""
    start: Ground
    end: Ground
    frame: int
    frames: int

    def at(self, t: int) -> Ground:
        """The ground shown at world frame t."""
        s = min(max((t - self.frame) / max(self.frames, 1), 0.0), 1.0)
        if s >= 1.0:
            return self.end
        lerp = lambda a, b: tuple(x + s * (y - x) for x, y in zip(a, b))
        return Ground(lerp(self.start.tilt, self.end.tilt), lerp(self.start.pivot, self.end.pivot))

    def over(self, t: int) -> bool:
        """From world frame t on, the ground is the end's."""
        return t >= self.frame + self.frames


@dataclass(frozen=True)
class Box:
    """A static obstacle standing on the floor: centre (x, z), size (width x along its own X, height,
    depth along its own Z) in m, turned by `yaw` degrees about +Y."""
    centre: tuple
    size: tuple
    yaw: float = 0.0

    def __post_init__(self):
        object.__setattr__(self, "centre", _finite(self.centre, 2, "obstacle centre (x, z m)", -1000, 1000))
        object.__setattr__(self, "size", _finite(self.size, 3, "obstacle size (x, y, z m)", *BOX_SIZE))
        object.__setattr__(self, "yaw", _finite((self.yaw,), 1, "obstacle yaw (degrees)", -360, 360)[0])

    def frame(self, dtype=torch.float64) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The box's rotation R (3, 3) (its axes as columns), centre c (3,) and half sizes (3,)."""
        a = math.radians(self.yaw)
        R = torch.tensor([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]], dtype=dtype)
        c = torch.tensor([self.centre[0], self.size[1] / 2, self.centre[1]], dtype=dtype)
        return R, c, torch.tensor(self.size, dtype=dtype) / 2

    def local(self, x: torch.Tensor, radius: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Points x (..., 22, 3) with spheres of radius (22,), in the box's frame: their coordinates q
        (..., 22, 3), the half sizes e (22, 3) of the box grown by each radius (a sphere is inside
        where |q| < e on every axis, by e - |q|), and the box's rotation R (3, 3) and centre c (3,)."""
        R, c, half = self.frame(x.dtype)
        return (x - c) @ R, half + radius.to(x.dtype)[:, None], R, c


@dataclass(frozen=True)
class Environment:
    ground: Ground = field(default_factory=Ground)
    boxes: tuple = ()

    def __post_init__(self):
        if len(self.boxes) > MAX_BOXES:
            raise ValueError(f"at most {MAX_BOXES} obstacles, got {len(self.boxes)}; remove some first")

    @property
    def plain(self) -> bool:
        """The flat floor and nothing on it."""
        return self.ground.flat and not self.boxes

    def plain_near(self, xz: torch.Tensor, margin: float) -> torch.Tensor:
        """(B,) bool: for points xz (B, 2) on the floor, the ground is flat and no box's footprint
        comes within `margin` m of them (measured from its centre less its half diagonal)."""
        far = torch.full((len(xz),), self.ground.flat, dtype=torch.bool)
        for b in self.boxes:
            reach = math.hypot(b.size[0], b.size[2]) / 2 + margin
            far &= (xz.double() - torch.tensor(b.centre, dtype=torch.float64)).norm(dim=-1) > reach
        return far

    def over_footprint(self, xz: torch.Tensor, grow: float) -> torch.Tensor:
        """(B,) bool: floor points xz (B, 2) over some box's footprint grown by `grow` m on every side
        (the box's own rectangle, turned with it: a long thin bar is near only across its length)."""
        if not self.boxes:
            return torch.zeros(len(xz), dtype=torch.bool)
        c, A, h = footprints(self, grow, torch.float64)
        return (_in_footprint_frames(xz.double(), c, A).abs() < h[None]).all(-1).any(-1)

    def describe(self, motion: GroundMotion | None = None) -> dict:
        """For clients (the protocol's `environment` message); motion: the ground turning to this
        one now (its start, and the world frames it takes), or None."""
        out = {"ground": {"tilt": list(self.ground.tilt), "pivot": list(self.ground.pivot)}}
        if motion is not None:
            out["ground"]["from"] = {"tilt": list(motion.start.tilt), "pivot": list(motion.start.pivot),
                                     "frame": motion.frame, "frames": motion.frames}
        return out | {"obstacles": [{"centre": list(b.centre), "size": list(b.size), "yaw": b.yaw} for b in self.boxes]}


FLAT = Environment()


def project_ground(x: torch.Tensor, x_prev: torch.Tensor, rest: torch.Tensor, ground: Ground,
                   friction: torch.Tensor | None = None) -> torch.Tensor:
    """(B, 22, 3): a joint of x whose centre is less than its resting height rest ((22,) or (B, 22)) above the
    plane moved onto that height at the place it had in x_prev along the plane (static friction);
    any other joint is itself. friction (B,): each body's Coulomb coefficient (None or inf: the
    joint is held whatever the slip): a joint whose slip along the plane since x_prev is more
    than friction times its depth under its resting height keeps the slip beyond that (kinetic
    friction, the position-level Coulomb law of position-based dynamics): the contact energy
    pulls it back along the plane at most friction times as hard as it pushes it up."""
    n = ground.normal(x.dtype)
    h = ground.height(x)
    r = rest.to(x.dtype)
    lift = r - ground.height(x_prev)  # x_prev moved along n onto the resting height
    p = x_prev + lift[..., None] * n
    if friction is not None and bool(torch.isfinite(friction).any()):
        slip = x - p
        slip = slip - (slip * n).sum(-1, keepdim=True) * n  # along the plane
        length = slip.norm(dim=-1)
        depth = (r - h).clamp(min=0.0)
        mu = friction.to(x.dtype)[:, None].expand_as(length)
        held = ~torch.isfinite(mu) | (length <= mu * depth)
        kept = torch.where(held, torch.zeros_like(length), 1.0 - mu.clamp(max=1e30) * depth / length.clamp_min(1e-12))
        p = p + kept[..., None] * slip
    return torch.where((h < r)[..., None], p, x)


def project_box(x: torch.Tensor, x_prev: torch.Tensor, radius: torch.Tensor, box: Box) -> torch.Tensor:
    """(B, 22, 3): a joint of x whose collision sphere (radius (22,)) is inside the box (grown by the
    radius) moved out through the face it came in by (the face x_prev is furthest outside of; the
    nearest face if x_prev was inside too), at x_prev's place on that face (static friction); any
    other joint is itself."""
    q, e, R, c = box.local(x, radius)
    qp = (x_prev - c) @ R  # box coordinates
    inside = ((q.abs() < e).all(-1))
    was_out = (qp.abs() - e).amax(-1) > 0
    ref = torch.where(was_out[..., None], qp, q)
    axis = (ref.abs() - e).argmax(-1, keepdim=True)  # the face: the axis the reference is most outside along
    side = torch.where(ref.gather(-1, axis) >= 0, 1.0, -1.0).to(x.dtype)
    held = qp.scatter(-1, axis, side * e.expand_as(q).gather(-1, axis))
    return torch.where(inside[..., None], held @ R.T + c, x)


def project_contact(x: torch.Tensor, x_prev: torch.Tensor, rest: torch.Tensor, radius: torch.Tensor,
                    env: Environment, friction: torch.Tensor | None = None) -> torch.Tensor:
    """The contact energy's projection: the ground (with each body's Coulomb coefficient friction
    (B,), None: static), then each box in turn (static)."""
    p = project_ground(x, x_prev, rest, env.ground, friction)
    for box in env.boxes:
        p = project_box(p, x_prev, radius, box)
    return p


def touching(x: torch.Tensor, rest: torch.Tensor, radius: torch.Tensor, env: Environment, margin: float) -> torch.Tensor:
    """(B,) bool: some joint of x (B, 22, 3) is within `margin` m of its resting height (22,) above
    the ground, or its collision sphere (radius (22,)) within `margin` of an obstacle."""
    near = (env.ground.height(x) < rest.to(x.dtype) + margin).any(-1)
    for box in env.boxes:
        q, e, _, _ = box.local(x, radius + margin)
        near |= (q.abs() < e).all(-1).any(-1)
    return near


def lift_above(J: torch.Tensor, ground: Ground) -> torch.Tensor:
    """(B, 3): how far to move each frame of joints J (B, 22, 3) along the ground's normal so that
    no joint centre is below the plane (zero where none is)."""
    return (-ground.height(J).amin(-1)).clamp(min=0.0)[..., None] * ground.normal(J.dtype)


def push_out_of_boxes(J: torch.Tensor, radius: torch.Tensor, env: Environment, rounds: int = 2) -> torch.Tensor:
    """(B, 3): how far to move each frame of joints J (B, 22, 3) so that no joint's collision
    sphere (radius (22,)) is inside a box: each round, the deepest sphere leaves through its
    nearest face and the whole body moves with it (zero where none is inside). A body is one rigid
    piece here, as lift_above moves it for the ground."""
    shift = torch.zeros(J.shape[0], 3, dtype=J.dtype)
    for _ in range(rounds):
        moved = False
        for box in env.boxes:
            q, e, R, _ = box.local(J + shift[:, None], radius)  # box coordinates (B, 22, 3)
            over = e - q.abs()  # (B, 22, 3) > 0 on every axis: inside
            depth, axis = over.amin(-1), over.argmin(-1)  # the nearest face's overlap, and its axis
            depth = torch.where((over > 0).all(-1), depth, torch.zeros_like(depth))
            deepest = depth.argmax(-1)  # (B,)
            rows = torch.arange(J.shape[0])
            d, a = depth[rows, deepest], axis[rows, deepest]
            if not bool((d > 0).any()):
                continue
            sign = torch.sign(q[rows, deepest, a])
            sign = torch.where(sign == 0, torch.ones_like(sign), sign)
            local = torch.zeros(J.shape[0], 3, dtype=J.dtype)
            local[rows, a] = sign * d
            shift = shift + local @ R.T
            moved = True
        if not moved:
            break
    return shift


def slide_out_of_boxes(J: torch.Tensor, before: torch.Tensor, radius: torch.Tensor, env: Environment,
                       rounds: int = 8) -> torch.Tensor:
    """(B, T, 3): the horizontal shift of each frame of segments J (B, T, 22, 3), which follow the
    frames `before` (B, 22, 3), that keeps every joint's collision sphere (radius (22,)) out of the
    boxes, for a body the motion model moves alone (not in physics mode): to it an obstacle is a
    wall, as to a game's character controller. Frame by frame, the shift so far is carried on (a
    body a wall stopped stays stopped while its model walks on, and slides along a wall it meets
    at an angle); then, each round, the sphere furthest inside leaves through the side face it came
    in by (the one it was furthest outside of the frame before, so a fast body does not pop through
    a thin wall; the nearest side face if it was inside then too), as does a sphere that went
    through the box since the frame before, and the whole body moves with it.
    Never up: the model's body cannot climb, so nothing keeps it on a box's top (physics mode
    steps on and over boxes). Zero where no box is near."""
    B, T = J.shape[:2]
    shift = torch.zeros(B, T, 3, dtype=J.dtype)
    if not env.boxes:
        return shift
    frames = [b.frame(J.dtype) for b in env.boxes]
    R = torch.stack([f[0] for f in frames])  # (n, 3, 3) each box's axes as columns
    c = torch.stack([f[1] for f in frames])  # (n, 3)
    e = torch.stack([f[2] for f in frames])[:, None, :] + radius.to(J.dtype)[None, :, None]  # (n, 22, 3) grown
    side_axes = torch.tensor([0, 2])

    def local(x):  # (B, 22, 3) -> (B, n, 22, 3) box coordinates
        return torch.einsum("bnjk,nkl->bnjl", x[:, None] - c[None, :, None], R)

    def meets(q, qp):  # (..., n, 22): inside now, or gone through since qp (a hand swung 25 cm a frame through a 10 cm wall)
        out = q.abs() >= e
        crossed = (q * qp < 0) & out & (qp.abs() >= e)  # on opposite sides of the box along an axis
        x_through = crossed[..., 0] & ~out[..., 1] & ~out[..., 2]
        z_through = crossed[..., 2] & ~out[..., 0] & ~out[..., 1]
        return ~out.any(-1) | x_through | z_through

    # the shift stays zero until a frame as the model made it meets a box: only such bodies are
    # stepped through (the others cost one test of all their frames at once)
    raw = local(J.flatten(0, 1)).unflatten(0, (B, T))
    raw_prev = torch.cat((local(before.to(J.dtype))[:, None], raw[:, :-1]), 1)
    hit = meets(raw, raw_prev).flatten(1).any(-1)
    if not bool(hit.any()):
        return shift
    if not bool(hit.all()):
        shift[hit] = slide_out_of_boxes(J[hit], before[hit], radius, env, rounds)
        return shift
    s = torch.zeros(B, 3, dtype=J.dtype)
    prev = before.to(J.dtype)
    rows = torch.arange(B)
    for t in range(T):
        qp = local(prev)
        for _ in range(rounds):
            q = local(J[:, t] + s[:, None])
            inside = meets(q, qp)  # (B, n, 22)
            if not bool(inside.any()):
                break
            was_out = ((qp.abs() - e)[..., side_axes].amax(-1) > -1e-9)[..., None]
            ref = torch.where(was_out, qp, q)[..., side_axes]  # (B, n, 22, 2)
            axis = (ref.abs() - e[..., side_axes]).argmax(-1, keepdim=True)  # 0: the box's X, 1: its Z
            side = torch.where(ref.gather(-1, axis) >= 0, 1.0, -1.0).to(J.dtype)
            # how far along the box's axis the sphere must go to reach that face
            need = side * e[..., side_axes].expand_as(ref).gather(-1, axis) - q[..., side_axes].gather(-1, axis)
            need = torch.where(inside[..., None], need, torch.zeros_like(need))[..., 0]  # (B, n, 22)
            flat = need.abs().flatten(1).argmax(-1)  # the furthest inside, over boxes and joints
            box, joint = flat // need.shape[2], flat % need.shape[2]
            d = need[rows, box, joint]
            ax_k = axis[rows, box, joint, 0]
            # a body whose spheres came into that box by different faces (an arm round a wall's
            # end: the shoulder on one side, the elbow in the wall, the hand beyond it) would be
            # pushed to and fro: it moves along the one box axis, and by the least, that leaves
            # every sphere in the box's span on the other axes on one side of it
            ins = inside[rows, box]  # (B, 22)
            face = axis[rows, box, :, 0] * 2 + (side[rows, box, :, 0] > 0).long()  # (B, 22)
            mixed = ((face != face[rows, joint][:, None]) & ins).any(-1)
            if bool(mixed.any()):
                qb, eb = q[rows, box], e[box]  # (B, 22, 3)
                within = qb.abs() < eb
                clear = []
                for k, others in ((0, [1, 2]), (2, [0, 1])):
                    span = within[..., others].all(-1)  # (B, 22)
                    for sg in (1.0, -1.0):  # leaving by the box's - face, then by its + face
                        clear.append(torch.where(span, eb[..., k] + sg * qb[..., k], torch.zeros_like(qb[..., k])).amax(1).clamp_min(0))
                clear = torch.stack(clear, -1)  # (B, 4): -X, +X, -Z, +Z
                # of these, the least that leaves no sphere inside nor taken through a box since
                # the frame before (a whole body moved across a thin wall is no way out either)
                sign = torch.tensor([-1.0, 1.0, -1.0, 1.0], dtype=J.dtype)
                way = (clear * sign)[..., None] * R[box][:, :, side_axes].repeat_interleave(2, -1).transpose(1, 2)  # (B, 4, 3)
                moved = J[:, t, None] + (s[:, None] + way)[:, :, None]  # (B, 4, 22, 3)
                stuck = meets(local(moved.flatten(0, 1)), qp.repeat_interleave(4, 0)).flatten(1).any(-1).view(B, 4)
                best = (clear + 1e3 * stuck).argmin(-1)
                whole = clear[rows, best] * torch.where(best % 2 == 1, 1.0, -1.0).to(J.dtype)
                d = torch.where(mixed, whole, d)
                ax_k = torch.where(mixed, best // 2, ax_k)
            ax = side_axes[ax_k]
            s = s + d[:, None] * R[box, :, ax]  # along that box axis (a column of R) in the world
        shift[:, t] = s
        prev = J[:, t] + s[:, None]
    return shift


def footprints(env: Environment, grow: float, dtype=torch.float64) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The boxes' footprints on the floor, each grown by `grow` m on every side: their centres c
    (n, 2) (x, z), axes A (n, 2, 2) (the box's X and Z as columns, in x, z) and half sizes h (n, 2).
    A point p is inside one where |(p - c) @ A| < h on both axes."""
    c = torch.tensor([b.centre for b in env.boxes], dtype=dtype).reshape(-1, 2)
    A = torch.stack([b.frame(dtype)[0][[0, 2]][:, [0, 2]] for b in env.boxes]) if env.boxes else torch.zeros(0, 2, 2, dtype=dtype)
    h = torch.tensor([(b.size[0] / 2 + grow, b.size[2] / 2 + grow) for b in env.boxes], dtype=dtype).reshape(-1, 2)
    return c, A, h


def _in_footprint_frames(p: torch.Tensor, c: torch.Tensor, A: torch.Tensor) -> torch.Tensor:
    """(P, n, 2): floor points p (P, 2) in the frame of each footprint (footprints' c, A)."""
    return torch.einsum("pk,nkl->pnl", p, A) - torch.einsum("nk,nkl->nl", c, A)[None]


def _crossing(p: torch.Tensor, q: torch.Tensor, c: torch.Tensor, A: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
    """(P, n) bool: the segment from p (P, 2) to q (P, 2) runs through the inside of footprint n, of
    half sizes h (n, 2), or (P, n, 2) per segment (Liang-Barsky clipping in its frame; running
    along a side or touching a corner does not count)."""
    a = _in_footprint_frames(p, c, A)
    d = torch.einsum("pk,nkl->pnl", q - p, A)
    lo = torch.zeros(a.shape[:2], dtype=p.dtype)
    hi = torch.ones(a.shape[:2], dtype=p.dtype)
    inner = (h if h.dim() == 3 else h[None]) - 1e-6
    for k in range(2):
        dk, ak = d[..., k], a[..., k]
        still = dk.abs() < 1e-12
        # parallel to this axis: through only if already between its two sides
        outside = still & (ak.abs() >= inner[..., k])
        t1 = torch.where(still, torch.full_like(ak, -1e9), (-inner[..., k] - ak) / torch.where(still, torch.ones_like(dk), dk))
        t2 = torch.where(still, torch.full_like(ak, 1e9), (inner[..., k] - ak) / torch.where(still, torch.ones_like(dk), dk))
        lo = torch.maximum(lo, torch.minimum(t1, t2))
        hi = torch.minimum(hi, torch.maximum(t1, t2))
        hi = torch.where(outside, torch.full_like(hi, -1.0), hi)
    return hi - lo > 1e-9


def route(start, goal, env: Environment, clearance: float) -> torch.Tensor:
    """(P, 2): the shortest way on the floor from `start` to `goal` (x, z) that keeps `clearance` m
    from every box's footprint: start, the corners of the grown footprints it goes round, goal
    (a visibility graph: shortest paths round convex obstacles bend only at their corners). Just
    (start, goal) when the straight line is clear, when no box stands between them, or when the
    goal is walled in. An end within clearance of a box (a body against a wall, a target next to
    one) is joined to the graph past that box's own footprint only, so it is not cut off."""
    s = torch.as_tensor(start, dtype=torch.float64).reshape(2)
    g = torch.as_tensor(goal, dtype=torch.float64).reshape(2)
    direct = torch.stack((s, g))
    if not env.boxes:
        return direct
    c, A, h = footprints(env, clearance)
    h0 = h - clearance  # the footprints themselves

    def inside(p, half):  # (P, n)
        return (_in_footprint_frames(p, c, A).abs() < half[None]).all(-1)

    ends = torch.stack((s, g))
    held = inside(ends, h)  # (2, n): an end within clearance of footprint n
    if not bool(_crossing(s[None], g[None], c, A, torch.where(held.any(0)[:, None], h0, h)).any()):
        return direct
    # the grown footprints' corners, 1 cm further out so that a path round one is not inside it
    signs = torch.tensor([[1.0, 1.0], [1.0, -1.0], [-1.0, 1.0], [-1.0, -1.0]], dtype=torch.float64)
    local = signs[None] * (h + 0.01)[:, None]  # (n, 4, 2)
    corners = (c[:, None] + torch.einsum("nkl,nml->nmk", A, local)).reshape(-1, 2)
    corners = corners[~inside(corners, h).any(-1)]  # a corner inside another box's grown footprint is no way
    nodes = torch.cat((ends, corners))  # 0: start, 1: goal
    P = len(nodes)
    i, j = torch.triu_indices(P, P, 1)
    # an edge leaving an end that is within clearance of a box only has to miss that box's own footprint
    half = h[None].expand(len(i), -1, -1).clone()
    for e in range(2):
        at_end = (i == e) | (j == e)
        half[at_end] = torch.where(held[e][None, :, None], h0[None], half[at_end])
    a, b = nodes[i], nodes[j]
    blocked = _crossing(a, b, c, A, half).any(-1)
    w = torch.full((P, P), math.inf, dtype=torch.float64)
    length = (a - b).norm(dim=-1)
    w[i[~blocked], j[~blocked]] = length[~blocked]
    w[j[~blocked], i[~blocked]] = length[~blocked]
    # Dijkstra from the start (a few dozen nodes)
    dist = torch.full((P,), math.inf, dtype=torch.float64)
    prev = torch.full((P,), -1, dtype=torch.long)
    dist[0] = 0.0
    done = torch.zeros(P, dtype=torch.bool)
    for _ in range(P):
        left = torch.where(done, torch.full_like(dist, math.inf), dist)
        u = int(left.argmin())
        if not math.isfinite(float(left[u])):  # every node left is unreachable
            break
        done[u] = True
        if u == 1:
            break
        alt = dist[u] + w[u]
        better = alt < dist
        dist = torch.where(better, alt, dist)
        prev = torch.where(better, torch.full_like(prev, u), prev)
    if not math.isfinite(float(dist[1])):
        return direct  # walled in: walk at it, the walls hold the body
    way = [1]
    while way[-1] != 0:
        way.append(int(prev[way[-1]]))
    return nodes[way[::-1]]


def way_ahead(start, direction, env: Environment, clearance: float, ahead: float, margin: float,
              beyond: float = 20.0) -> torch.Tensor | None:
    """Where a walk from `start` (x, z) along `direction` (x, z) is headed when an obstacle stands
    in the way within `ahead` m (a footprint grown by `margin`): the first point on that line at
    least `ahead` m on and clear of every footprint grown by `clearance` (so that a way round can
    end there), None when the way is open or no such point lies within `beyond` m (walled in).
    A margin under the clearance is hysteresis: a body that went round a corner at the clearance
    and strays back a little is not sent round it again."""
    s = torch.as_tensor(start, dtype=torch.float64).reshape(2)
    d = torch.as_tensor(direction, dtype=torch.float64).reshape(2)
    n = float(d.norm())
    if not env.boxes or n < 1e-9 or ahead <= 0:
        return None
    d = d / n
    c, A, h = footprints(env, margin)
    if not bool(_crossing(s[None], (s + ahead * d)[None], c, A, h).any()):
        return None
    t = torch.arange(ahead, beyond + 1e-9, 0.1, dtype=torch.float64)
    p = s[None] + t[:, None] * d[None]
    clear = ~env.over_footprint(p, clearance)
    return p[int(clear.nonzero()[0])] if bool(clear.any()) else None


def aim_round(start, goal, env: Environment, clearance: float, lookahead: float) -> tuple[torch.Tensor, bool]:
    """Where to head for `goal` (x, z) from `start` with obstacles about: the goal itself, True,
    when the straight way is open (route); else, False, the point `lookahead` m along the way
    (pure pursuit: a body heading there turns round the corner as it nears it instead of
    slowing to arrive at it), or the way's first corner if the line to that point would cut
    through a box's footprint grown by half the clearance. clearance <= 0: the goal, True (no
    routing)."""
    s = torch.as_tensor(start, dtype=torch.float64).reshape(2)
    g = torch.as_tensor(goal, dtype=torch.float64).reshape(2)
    if clearance <= 0 or not env.boxes:
        return g, True
    way = route(s, g, env, clearance)
    if len(way) == 2:
        return g, True
    legs = (way[1:] - way[:-1]).norm(dim=-1)
    ends = legs.cumsum(0)
    k = min(int((ends < lookahead).sum()), len(legs) - 1)  # the leg the point lies on
    into = (lookahead - (float(ends[k - 1]) if k else 0.0)) / max(float(legs[k]), 1e-9)
    point = way[k] + min(max(into, 0.0), 1.0) * (way[k + 1] - way[k])
    c, A, h = footprints(env, clearance / 2)
    if bool(_crossing(s[None], point[None], c, A, h).any()):
        return way[1], False
    return point, False
