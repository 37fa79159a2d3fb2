"""The served world: a Crowd, the commands of the protocol, a 30-fps clock, recording and the
event log. No sockets here: the server and the headless replay both drive a World.

Threading: the server's event loop calls `apply` and `tick`; a worker thread calls `generate`.
Both hold `lock` while they touch the crowd; the diffusion itself runs outside the lock.
"""
from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections import deque
from dataclasses import dataclass, field

import torch

from ..body import rotations as rot
from ..body.skeleton import JOINT_NAMES
from ..body.motion_state import FPS, unpack
from ..model.checkpoint import Motor
from ..physics.environment import aim_round
from ..runtime.crowd import IMPULSE_PRESETS, Crowd, RuntimeConfig
from ..runtime.sampler import Cancelled
from . import protocol as P

MAX_AVATARS = 512  # the most a world holds however fast the machine (Server measures its own cap)
# frames kept queued ahead of playback: half a second, so a batch of many avatars that come due
# together has time to finish (served, 128 avatars for 60 s: 242 of 1,800 ticks stalled with 8, 1
# with 15). A command cuts the queue anyway, so a deeper queue does not slow reactions.
LOOKAHEAD = 15
EVENTS_KEPT = 20000  # the event history is a ring: the newest commands, about 8 MB at most
# a batch that fails this many times in a row is given up: its avatars are stood up with physics
# off (World.generate), the clients told. Before, the server's worker retried it forever and those
# avatars stood frozen while every other one moved. A batch of several that fails is first tried
# one avatar at a time, so that only the avatars that fail alone are given up
FAILURES_BEFORE_RESET = 3


class CommandError(ValueError):
    """A well-formed message whose request cannot be carried out."""


@dataclass
class Target:
    position: torch.Tensor  # (2,) world x, z
    speed: float


@dataclass
class World:
    motor: Motor
    config: RuntimeConfig = field(default_factory=RuntimeConfig)
    seed: int = 0
    record_seconds: float = 60.0

    adaptors: list = field(default_factory=list)  # AdaptedDenoisers for labels, styles or targets
    range_of_motion: object = None  # physics mode's joint limits (physics.limits.RangeOfMotion)
    max_avatars: int = MAX_AVATARS  # spawns beyond are refused (the server sets what it keeps in real time)

    def __post_init__(self):
        self.lock = threading.RLock()
        self.crowd = Crowd(self.motor, self.config, self.seed, self.adaptors, self.range_of_motion)
        # frames kept when a command cuts an avatar's queue, shown while its new segment is made
        # (Crowd._changed): served, set per command from the clock (frames_to_keep_now); offline
        # and in replays, from the script
        self.crowd.keep_on_cut = 2
        if self.motor.net.cfg.persona:  # the text encoder loads in about a second: not at the first command
            from ..model.text import embed_texts
            embed_texts(["a person"])
        self.frame = 0
        self.targets: dict[int, Target] = {}
        self.history: dict[int, deque] = {}
        # the commands applied, with their frame: a replayable script (the newest EVENTS_KEPT)
        self.events: deque[dict] = deque(maxlen=EVENTS_KEPT)
        self.events_total = 0
        self.stalls = 0  # ticks at which some avatar had no frame ready
        # the server's clock: when its next tick runs (time.perf_counter), how long a batch takes
        # now, and since when the worker's batch in flight runs; None offline (no wall clock)
        self.next_tick: float | None = None
        self.segment_seconds: float | None = None
        self.generating_since: float | None = None
        self.tick_allowance = 0.0  # how much later than next_tick the clock may still tick (Pacer)
        self.cut_pending = False  # a command emptied a queue (kept no frame): the clock ticks when it refills
        # the row budget each batch was made with, from the frame it changed (a replay draws the
        # same: run_offline); kept beside the events, which are the commands
        self.budgets: deque[dict] = deque(maxlen=EVENTS_KEPT)
        # served: seconds a batch row takes now (the generation worker's measure, as segment_seconds);
        # from the next batch on, its draws are cut to what fits the frames queued (generate). None offline
        self.row_cost: float | None = None
        self.failures = 0  # batches failed in a row (generate)
        # the avatars of a failed batch not yet tried alone (generate makes their segments one at a
        # time), and whether that search has run since the last batch of several went through: a
        # batch that fails again after it is given up whole (its avatars fail only together)
        self.suspects: list[int] = []
        self.searched = False
        # what clients are told of avatars a failing batch stood up (the server sends and empties it)
        self.notices: list[dict] = []

    # ------------------------------------------------------------ commands
    def apply(self, cmd: dict, log: bool = True) -> dict:
        """Carry out one validated command; returns the ack payload. Raises CommandError."""
        kind = cmd["type"]
        with self.lock:
            if self.next_tick is not None and self.segment_seconds is not None:
                self.crowd.keep_on_cut = self.frames_to_keep_now(time.perf_counter())
            res = getattr(self, f"_cmd_{kind}")(cmd)
            if self.crowd.keep_on_cut == 0 and self.crowd.needs_frames(1):
                self.cut_pending = True
            if log:  # with the frames its cut kept, so a replay cuts as this world did
                self.events.append({"frame": self.frame, "t": self.frame / FPS, "cmd": cmd, "keep": self.crowd.keep_on_cut})
                self.events_total += 1
        return res or {}

    def _avatar(self, cmd) -> int:
        i = cmd.get("avatar", 0)
        if i not in self.crowd:
            raise CommandError(f"no avatar {i}; avatars are {self.crowd.ids()}")
        return i

    def _cmd_spawn(self, cmd):
        if len(self.crowd) >= self.max_avatars:
            raise CommandError(f"this world keeps at most {self.max_avatars} avatars in real time on this machine; "
                               "remove one first (serve --max-avatars sets the cap)")
        pos = cmd.get("position", [1.0 * len(self.crowd), 0.0])
        shape = cmd.get("shape")
        i = self.crowd.spawn(shape=torch.tensor(shape, dtype=torch.float32) if shape is not None else None,
                             position=(float(pos[0]), float(pos[1])), yaw=float(cmd.get("yaw", 0.0)))
        self.history[i] = deque(maxlen=int(self.record_seconds * FPS))
        return {"avatar": i}

    def _cmd_remove(self, cmd):
        i = self._avatar(cmd)
        self.crowd.remove(i)
        self.targets.pop(i, None)
        self.history.pop(i, None)

    def _cmd_impulse(self, cmd):
        i = self._avatar(cmd)
        if cmd["preset"] not in IMPULSE_PRESETS:
            raise CommandError(f"unknown preset {cmd['preset']!r}; presets are {sorted(IMPULSE_PRESETS)}")
        self.crowd.impulse(i, cmd["preset"], float(cmd.get("scale", 1.0)))

    def _cmd_push(self, cmd):
        i = self._avatar(cmd)
        j = cmd["joint"]
        if isinstance(j, str) and j not in JOINT_NAMES:
            raise CommandError(f"unknown joint {j!r}; joints are {JOINT_NAMES}")
        self.crowd.push(i, j, cmd["velocity"], cmd.get("frame", "world"))

    def _cmd_goal(self, cmd):
        i = self._avatar(cmd)
        self.targets.pop(i, None)
        self.crowd.set_goal(i, cmd.get("velocity"), cmd.get("facing"))

    def _cmd_target(self, cmd):
        i = self._avatar(cmd)
        pos = cmd.get("position")
        if any(ad.cfg.control == "target" for ad in self.crowd.adaptors):  # a reaching adaptor walks there by itself
            self.crowd.set_target(i, pos, _scale(cmd))
            return
        if pos is None:
            self.targets.pop(i, None)
            self.crowd.set_goal(i, None)
            return
        self.targets[i] = Target(torch.tensor(pos, dtype=torch.float32), float(cmd.get("speed", 1.2)))
        self._steer_to_target(i)

    def _cmd_label(self, cmd):
        i = self._avatar(cmd)
        try:
            self.crowd.set_label(i, cmd["label"], _scale(cmd))
        except ValueError as e:
            raise CommandError(str(e)) from None

    def _cmd_persona(self, cmd):
        i = self._avatar(cmd)
        try:
            self.crowd.set_persona(i, cmd["description"])
        except ValueError as e:
            raise CommandError(str(e)) from None

    def _cmd_reset(self, cmd):
        """Stand the avatar(s) up where they are, controls released."""
        ids = [self._avatar(cmd)] if "avatar" in cmd else self.crowd.ids()
        for i in ids:
            self.crowd.reset(i)
            self.targets.pop(i, None)

    def _physics(self, call, *args, **kw):
        try:
            call(*args, **kw)
        except ValueError as e:
            raise CommandError(str(e)) from None

    def _cmd_physics(self, cmd):
        self._physics(self.crowd.set_physics, self._avatar(cmd), cmd["on"])

    def _cmd_force(self, cmd):
        self._physics(self.crowd.apply_force, self._avatar(cmd), cmd["joint"], cmd["force"], cmd["seconds"])

    def _cmd_spring(self, cmd):
        self._physics(self.crowd.set_spring, self._avatar(cmd), cmd["joint"], cmd["target"], cmd.get("stiffness", 400.0))

    def _cmd_ball(self, cmd):
        self._physics(self.crowd.throw, self._avatar(cmd), cmd["position"], cmd["velocity"], cmd.get("mass", 1.0),
                      cmd.get("radius", 0.11))

    def _cmd_ground(self, cmd):
        self._physics(self.crowd.set_ground, cmd["tilt"], cmd.get("pivot", (0.0, 0.0)), cmd.get("seconds", 0.0))

    def _cmd_obstacle(self, cmd):
        try:
            return {"obstacle": self.crowd.add_obstacle(cmd["centre"], cmd["size"], cmd.get("yaw", 0.0))}
        except ValueError as e:
            raise CommandError(str(e)) from None

    def _cmd_remove_obstacle(self, cmd):
        self._physics(self.crowd.remove_obstacle, cmd.get("obstacle"))

    def environment_payload(self) -> dict:
        """The ground (turning: with where it turns from) and obstacles (the `environment` message,
        the welcome's field and, without its type, the stats')."""
        return {"type": "environment", **self.crowd.environment.describe(self.crowd.turning())}

    def balls_payload(self) -> list[dict]:
        """The balls shown now, each with the avatar it is simulated with (for the stream)."""
        out = []
        for i in self.crowd.ids():
            for b in self.crowd.balls(i):
                out.append({"avatar": i, "position": [round(float(v), 4) for v in b.position], "radius": b.radius})
        return out

    def _cmd_seed(self, cmd):
        """Reseed every avatar's noise (and those spawned later) for a reproducible continuation."""
        self.crowd.reseed(int(cmd["seed"]))

    # ------------------------------------------------------------ clock
    def _steer_to_target(self, i: int) -> None:
        """The magnet: a goal velocity towards the target, slowing within a metre of it."""
        tg = self.targets[i]
        pelvis = self.crowd.state(i)[[0, 2]]
        cfg = self.crowd.cfg
        aim, _ = aim_round(pelvis, tg.position, self.crowd.environment, cfg.route_clearance, cfg.route_lookahead)
        d = (aim - pelvis.double()).to(tg.position.dtype)  # round an obstacle in the way
        cur = self.crowd.goal_velocity(i)
        dist = float(d.norm())
        if dist < 0.25:
            if cur is not None:
                self.crowd.set_goal(i, None)
            return
        v = d / dist * tg.speed * min(1.0, dist)
        if cur is None or not torch.equal(cur[[0, 2]], v):
            self.crowd.set_goal(i, v.tolist(), route=False)  # the crowd cuts only for a noticeable change

    def frames_to_keep_now(self, now: float) -> int:
        """The frames a command's cut keeps at time `now`: as many as the clock shows before the
        new segment can be ready (the batch in flight first, then one batch, with CUT_MARGIN). None
        when it is ready before the next tick may come (`tick_allowance` past `next_tick`): the
        clock then shows it as soon as it is ready (Pacer)."""
        period = 1.0 / FPS
        ready = now + self.segment_seconds * (1.0 + CUT_MARGIN[0]) + CUT_MARGIN[1]
        if self.generating_since is not None:
            ready += max(0.0, self.generating_since + self.segment_seconds - now)
        if ready <= self.next_tick + self.tick_allowance:
            return 0
        return min(MAX_KEEP, math.ceil((ready - self.next_tick - self.tick_allowance) / period))

    def frames_ready(self) -> bool:
        """Whether every avatar has a frame to show at a tick now."""
        with self.lock:
            return not self.crowd.needs_frames(1)

    def needs_generation(self) -> bool:
        with self.lock:
            return self.crowd.needs_frames(LOOKAHEAD)

    def generate(self) -> None:
        """One batched segment for the avatars running low (worker thread)."""
        with self.lock:
            # with the avatars that run low, those that would within a segment: the crowd stays in
            # phase, one batch per segment instead of many small ones each waiting on the other
            # (a 1-hour soak, 8 avatars on one core, before: 4 % of ticks had an avatar stalled)
            if self.row_cost is not None:  # served: the batch must be ready before the shortest queue runs out
                queued = min((len(a.queue) for a in self.crowd.avatars.values()), default=LOOKAHEAD)
                self.crowd.max_rows = rows_within(self.row_cost, self.config.draw_budget, queued)
            self.suspects = [i for i in self.suspects if i in self.crowd]
            only = set(self.suspects[:1]) if self.suspects else None
            job = self.crowd.prepare(LOOKAHEAD + self.motor.net.cfg.frames, only)
            if job is None:
                if self.suspects:  # it needs no segment now (a command filled its queue): nothing to try
                    self.suspects.pop(0)
                return
            if job.max_rows != (self.budgets[-1]["max_rows"] if self.budgets else None):
                self.budgets.append({"frame": self.frame, "max_rows": job.max_rows})
            self.generating_since = time.perf_counter()
        try:  # a command that cuts every avatar of the batch stops it: the cut segment starts sooner
            seg = self.crowd.compute(job, cancelled=lambda: self.crowd.stale(job))
        except BaseException as e:
            with self.lock:
                self.crowd.abandon(job)
                self.generating_since = None
            if isinstance(e, Cancelled):
                return
            if not isinstance(e, Exception):  # KeyboardInterrupt, SystemExit
                raise
            with self.lock:
                self.failures += 1
                if len(job.avatars) > 1 and not self.searched:  # which of them fails it? each alone
                    self.suspects, self.searched, self.failures = list(job.avatars), True, 0
                    raise
                if self.failures < FAILURES_BEFORE_RESET:
                    raise
                self._give_up(job, e)
            return
        with self.lock:
            self.crowd.commit(job, seg)
            self.generating_since = None
            self.failures = 0
            if self.suspects and job.avatars == self.suspects[:1]:
                self.suspects.pop(0)  # not this one
            elif not self.suspects and len(job.avatars) > 1:
                self.searched = False

    def _give_up(self, job, error: Exception) -> None:
        """The batch failed FAILURES_BEFORE_RESET times: its avatars are stood up where they are,
        physics off (as the commands physics off and reset, logged, so a replay does the same), and
        a notice for the clients names them and the error. The world goes on."""
        with self.lock:
            ids = [i for i in job.avatars if i in self.crowd]  # (one row each; a removed one is gone)
            for i in ids:
                self.apply({"type": "physics", "avatar": i, "on": False})
                self.apply({"type": "reset", "avatar": i})
            self.failures = 0
            self.suspects = [i for i in self.suspects if i not in ids]
            self.notices.append({"type": "error", "id": None, "avatars": ids, "error": (
                f"generation failed {FAILURES_BEFORE_RESET} times in a row for avatars {ids} "
                f"({type(error).__name__}: {error}); they were stood up where they are with physics off. "
                "Please report it with the commands (GET /api/events), which replay it")})

    def tick(self) -> dict[int, torch.Tensor]:
        """Advance the clock one frame: every avatar with a frame ready shows it (the others hold
        their pose and count a stall). Returns the shown states."""
        with self.lock:
            self.frame += 1
            self.cut_pending = False
            out, stalled = self.crowd.advance()
            for i, x in out.items():
                self.history[i].append(x)
            if stalled:
                self.stalls += 1
            if self.frame % 5 == 0:
                for i in list(self.targets):
                    self._steer_to_target(i)
            return out

    def run_offline(self, frames: int, script: list[dict] | None = None, budgets: list[dict] | None = None) -> None:
        """Deterministic replay on a virtual clock: commands at their frames, generation inline;
        budgets: the recorded server's row budgets from their frames on (script()'s), or None."""
        script = sorted(script or [], key=lambda e: e["frame"])
        budgets = sorted(budgets or [], key=lambda e: e["frame"])
        k = b = 0
        for _ in range(frames):
            while b < len(budgets) and budgets[b]["frame"] <= self.frame:  # the recorded server's row budget
                self.crowd.max_rows = budgets[b]["max_rows"]
                b += 1
            while k < len(script) and script[k]["frame"] <= self.frame:
                keep = script[k].get("keep")
                if keep is not None:  # the frames the recorded server's cut kept
                    self.crowd.keep_on_cut = keep
                self.apply(P.validate_command(script[k]["cmd"]))
                k += 1
            tries = 0
            while self.needs_generation():
                try:
                    self.generate()
                except Exception:  # as the server's worker: again, until generate gives the batch up
                    tries += 1  # (each avatar of a failing batch may be tried alone, FAILURES_BEFORE_RESET times)
                    if tries > (len(self.crowd) + 2) * FAILURES_BEFORE_RESET:  # giving up did not help: a bug to see
                        raise
            self.tick()

    # ------------------------------------------------------------ output
    def frame_payload(self, states: dict[int, torch.Tensor]) -> tuple[list[int], torch.Tensor, torch.Tensor]:
        """ids, joint positions (A, 22, 3) world metres, local rotation quaternions (A, 22, 4) x,y,z,w
        (joint 0: the pelvis's world rotation)."""
        ids = sorted(states)
        if not ids:
            return [], torch.zeros(0, 22, 3), torch.zeros(0, 22, 4)
        X = torch.stack([states[i] for i in ids])
        u = unpack(X)
        R = u.rotations
        q = rot.matrix_to_quat(R)  # w, x, y, z
        return ids, u.joints, torch.cat((q[..., 1:], q[..., :1]), -1)

    def recording(self, i: int, seconds: float | None = None) -> torch.Tensor:
        with self.lock:
            if i not in self.history:
                raise CommandError(f"no avatar {i}")
            h = list(self.history[i])
        if seconds is not None:
            h = h[-max(1, int(seconds * FPS)):]
        if not h:
            raise CommandError(f"avatar {i} has no recorded frames yet")
        return torch.stack(h)

    def script(self) -> dict:
        """The event history as a script for `serve --headless --script` (a copy, taken under the
        lock; serialise it off the event loop)."""
        with self.lock:
            ev = list(self.events)
            return {"seed": self.seed, "frames": self.frame, "keep_on_cut": self.crowd.keep_on_cut, "events": ev,
                    "events_dropped": self.events_total - len(ev), "budgets": list(self.budgets)}

    def stats(self) -> dict:
        return {"type": "stats", "frame": self.frame, "avatars": len(self.crowd),
                "gen_ms": round(1000 * self.crowd.timings.get("total", 0.0), 1), "stalls": self.stalls,
                "max_rows": self.crowd.max_rows, "model": self.motor.name,
                "steps": self.crowd.cfg.steps,
                # in physics mode now: by command, or near a low obstacle (RuntimeConfig.step_over)
                "simulated": sorted(i for i, a in self.crowd.avatars.items() if a.physics)}



MAX_KEEP = 4  # frames a cut keeps at most (133 ms)
# a batch may run this much longer than the recent average (fraction, seconds) before a command's
# cut stalls a frame: this machine's segment times vary by 20-30 % between runs
CUT_MARGIN = (0.3, 0.004)


@dataclass
class Pacer:
    """The served clock's schedule, 30 ticks a second on average. A tick may come early, when a
    command's new segment is ready before its time, or late, waiting for a frame not ready yet,
    each by at most `max_drift` from the nominal schedule; a tick that moved sets the phase of the
    ticks after it, and the schedule drifts back to nominal by at most `correction` a tick. So a
    command shows as soon as its segment is made instead of at the next tick after that (the
    reaction through the socket: one avatar, 2 cores, 67 ms before), and the frame rate over time
    stays the clock's whatever the commands do. A tick moves at most once in `calm` ticks: a
    stick sending goals at 60 Hz moved nearly every tick otherwise (frame gaps at the client: 95th
    percentile 52 ms instead of 39), while a push or a click is seldom more often than that.

    Times are time.perf_counter() seconds. `wait` says what to do now, `ticked` records a tick."""
    period: float
    next_t: float  # when the next tick is due on the current phase
    nominal: float  # when it is due on the nominal schedule
    last: float  # when the last tick ran
    max_drift: float = 1.0 / FPS
    min_interval: float = 0.5 / FPS  # an early tick never comes sooner than this after the last
    correction: float = 0.002  # seconds a tick moves back toward nominal (6 % of a frame)
    calm: int = 15  # ticks from one moved tick to the next
    since_moved: int = 15

    @classmethod
    def start(cls, now: float, period: float = 1.0 / FPS) -> "Pacer":
        return cls(period, now, now, now - period)

    def allowance(self) -> float:
        """How much later than next_t the next tick may still come."""
        if self.since_moved < self.calm:
            return 0.0
        return max(0.0, self.nominal + self.max_drift - self.next_t)

    def wait(self, now: float, frames_ready: bool, cut_pending: bool) -> float:
        """Seconds to wait (or until woken by a committed segment) before asking again; 0: tick now.
        frames_ready: every avatar has a frame to show; cut_pending: a command emptied a queue
        since the last tick."""
        free = self.since_moved >= self.calm
        if now < self.next_t:
            if cut_pending and frames_ready and free:  # a command's segment is ready: show it early
                earliest = max(self.last + self.min_interval, self.nominal - self.max_drift)
                return max(0.0, earliest - now) if earliest < self.next_t else self.next_t - now
            return self.next_t - now
        if not frames_ready and free:  # due, with a frame missing: wait for it while drift allows
            return max(0.0, self.nominal + self.max_drift - now)
        return 0.0

    def ticked(self, now: float) -> None:
        """A tick ran at `now`: a tick off its phase (early, or late past sleep's own lateness)
        sets the phase of the next ones."""
        moved = now < self.next_t or now > self.next_t + 0.25 * self.period
        self.since_moved = 0 if moved else self.since_moved + 1
        self.next_t = (now if moved else self.next_t) + self.period
        self.nominal += self.period
        if now - self.nominal > 1.0:  # fell far behind (the machine paused): start over from now
            self.next_t = self.nominal = now + self.period
        drift = self.next_t - self.nominal
        self.next_t -= max(-self.correction, min(self.correction, drift))
        self.last = now


def frames_to_keep(seconds: float, cap: int = MAX_KEEP) -> int:
    """The frames a cut keeps to cover `seconds` of segment generation: at least 1, at most cap."""
    return max(1, min(cap, math.ceil(seconds * FPS)))


def rows_within(seconds: float, budget: float, frames: int) -> int | None:
    """The most rows a batch may have to be made within `budget` of the `frames` it makes, when a
    row takes `seconds` (a batch's time over its rows: its fixed cost counted per row, so a small
    batch is cut a little early rather than late); at least 1; None when the budget is 0 (never cut)."""
    if budget <= 0:
        return None
    return max(1, int(budget * frames / FPS / max(seconds, 1e-6) + 1e-9))


def measure_capacity(motor: Motor, config: RuntimeConfig, adaptors=None, probe: int = 8) -> tuple[int, int, str]:
    """How many avatars this machine keeps in real time, and how many frames a cut must keep.

    Times one segment for 1 and for `probe` avatars (after a warm-up), fits cost = a + b x avatars
    and keeps the batch within 60 % of a segment's 0.5 s (the clock, encoding and this machine's
    noise take the rest). Returns (cap, keep_on_cut, a line for the log)."""
    crowd = Crowd(motor, config, 0, adaptors)
    crowd.warm()  # the avatars' first segments then do not trace the post-processing graphs
    for k in range(probe):
        crowd.spawn(position=(1.0 * k, 0.0))

    def seconds(n: int) -> float:
        job = crowd.prepare(10**9)  # every avatar, the first n of them timed
        job = dataclasses.replace(job, **{k: v[:n] for k, v in vars(job).items() if isinstance(v, (list, torch.Tensor))})
        t0 = time.perf_counter()
        crowd.compute(job)
        return time.perf_counter() - t0

    seconds(1)
    t1 = min(seconds(1) for _ in range(2))
    seconds(probe)  # (a first call at a batch size sets up its kernels)
    tp = seconds(probe)
    per = max((tp - t1) / (probe - 1), 1e-4)
    seg = motor.net.cfg.frames  # new frames per segment (x0, the frame before them, is not repeated)
    budget = 0.6 * seg / FPS
    cap = max(1, min(MAX_AVATARS, int((budget - (t1 - per)) / per)))
    keep = frames_to_keep(t1, 3)
    return cap, keep, (f"a segment takes {1e3 * t1:.0f} ms for 1 avatar, {1e3 * tp:.0f} ms for {probe}: "
                       f"this machine keeps {cap} avatars in real time; a command keeps {keep} queued frame(s)")


def _scale(cmd: dict) -> float | None:
    """A label or target command's adaptor scale; None (not given): the adaptor's own default."""
    return None if cmd.get("scale") is None else float(cmd["scale"])
