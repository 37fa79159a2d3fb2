"""`eval control` (supplementary Table A2), `eval impulses` (Table 2 + success per preset) and
`bench` (Table A6 columns, crowd throughput, reaction latency)."""
from __future__ import annotations

import dataclasses

import math
import statistics
import time

import torch

from ..body.skeleton import JOINT_INDEX
from ..data.cache import MotionCache
from ..data.dataset import SegmentConfig, SegmentDataset
from ..body.motion_state import FPS, horizontal, joints_of
from ..model.checkpoint import Motor
from ..runtime.crowd import IMPULSE_PRESETS, Crowd, RuntimeConfig
from ..runtime.guidance import facing_of
from ..runtime.sampler import bfloat16_units
from . import metrics as M
from .realism import BodyCheck, format_body, rollout

DIRECTIONS = {"forward": (0.0, 1.0), "left": (1.0, 0.0), "right": (-1.0, 0.0), "back": (0.0, -1.0)}


def initial_states(caches: list[MotionCache] | None, n: int, seed: int):
    """Held-out real initial states with random shapes, or (without data) standing avatars."""
    if caches:
        ds = SegmentDataset(caches, SegmentConfig(split="heldout", mirror=False))
        x, shapes = ds.sample(n, torch.Generator().manual_seed(seed))
        return x[:, 0], shapes, "held-out Bandai initial states"
    from ..runtime.crowd import standing_state
    return torch.stack([standing_state() for _ in range(n)]), torch.zeros(n, 6), "standing initial states"


def control(motor: Motor, caches, n: int = 45, seconds: float = 3.0, seed: int = 0,
            cfg: RuntimeConfig | None = None, personas: list[str] | None = None) -> tuple[list[dict], str, dict]:
    """Goals in the body frame of each initial state (forward/left/right/back x 1 and 4 m/s);
    errors measured after 1 s: mean pelvis-velocity error (m/s) and facing error (|z - r|), on
    the exported body. personas: descriptions a persona model's avatars take in turn (steering
    characters, as WASD does in the studio). Returns the rows, what the initial states are, and
    the one-body figures."""
    cfg = cfg or RuntimeConfig()
    if personas and not motor.net.cfg.persona:
        raise ValueError(f"{motor.name} has no persona condition: --persona needs a persona model "
                         "(models/primal-bandai-persona)")
    check = BodyCheck()
    init, shapes, what = initial_states(caches, n, seed)
    from ..body.motion_state import canonical_transform
    R = canonical_transform(init.double()).R.float()  # body -> world yaw per initial state
    rows = []

    def characters(crowd, seg):
        if seg == 0 and personas:
            for k, i in enumerate(sorted(crowd.avatars)):
                crowd.set_persona(i, personas[k % len(personas)])

    base = rollout(motor, init, shapes, int(seconds * FPS), cfg, seed, characters, check=check)
    rows.append({"goal": "none (unguided)", "vel_err": float("nan"), "dir_err": float("nan"), "ASR": M.asr(joints_of(base))})
    for name, (dx, dz) in DIRECTIONS.items():
        for speed in (1.0, 4.0):
            g_world = torch.stack([R[k] @ torch.tensor([dx * speed, 0.0, dz * speed]) for k in range(n)])

            def controls(crowd, seg, g_world=g_world):
                characters(crowd, seg)
                if seg == 0:
                    for k, i in enumerate(sorted(crowd.avatars)):
                        crowd.set_goal(i, (float(g_world[k, 0]), float(g_world[k, 2])))

            X = rollout(motor, init, shapes, int(seconds * FPS), cfg, seed, controls, check=check)
            J = joints_of(X)
            after = int(FPS)  # after 1 s
            # mean joint velocity over each remaining second, horizontal, vs the goal
            v = (J[:, after + 1:] - J[:, after:-1]).mean(-2) * FPS  # (n, T, 3)
            g = g_world[:, None, :]
            vel_err = float(horizontal(v - g).norm(dim=-1).mean())
            z, _ = facing_of(X[:, after:])
            r = g / g.norm(dim=-1, keepdim=True)
            dir_err = float((z - r).norm(dim=-1).mean())
            rows.append({"goal": f"{name} {speed:g} m/s", "vel_err": vel_err, "dir_err": dir_err, "ASR": M.asr(J)})
    return rows, what, check.summary()


def format_control(rows: list[dict], what: str, n: int, seconds: float, body: dict) -> str:
    guided = [r for r in rows if not math.isnan(r["vel_err"])]
    mean = {k: sum(r[k] for r in guided) / len(guided) for k in ("vel_err", "dir_err", "ASR")}
    out = [f"guidance control (supplementary Table A2): {n} {what} x {seconds:g} s, errors after 1 s",
           f"{'goal':18s} {'err.vel (m/s)':>14s} {'err.dir':>8s} {'ASR':>6s}"]
    for r in rows:
        out.append(f"{r['goal']:18s} {r['vel_err']:14.3f} {r['dir_err']:8.3f} {r['ASR']:6.3f}")
    out.append(f"{'mean (guided)':18s} {mean['vel_err']:14.3f} {mean['dir_err']:8.3f} {mean['ASR']:6.3f}"
               f"   PRIMAL InContext: 1.040 0.140 0.109; ASR vs unguided +{mean['ASR'] - rows[0]['ASR']:.3f}")
    out.append(format_body(body))
    return "\n".join(out)


# ---------------------------------------------------------------- impulses
def _pitch_passes_180(X: torch.Tensor) -> torch.Tensor:
    """Back flip detector: the body's up axis (pelvis -> neck) turns past horizontal and over,
    i.e. its cumulative pitch rotation exceeds 180 degrees."""
    J = joints_of(X)
    up = J[..., JOINT_INDEX["neck"], :] - J[..., 0, :]
    fwd0 = facing_of(X[:, 0])[0]  # initial facing (B, 3)
    # pitch angle of the trunk in the sagittal plane (forward, up)
    a = _unwrap(torch.atan2((up * fwd0[:, None]).sum(-1), up[..., 1]))
    return (a - a[:, :1]).abs().amax(1) > math.pi


def _unwrap(a: torch.Tensor) -> torch.Tensor:
    d = torch.diff(a, dim=1)
    d = (d + math.pi) % (2 * math.pi) - math.pi
    return torch.cat((a[:, :1], a[:, :1] + torch.cumsum(d, 1)), 1)


KICK_PELVIS = 0.65  # m: a standing body's pelvis (DeepMimic's kick keeps it at 0.80-0.94 m)
KICK_LEAN = math.radians(60)  # the trunk's largest lean from upright in a kick


def impulse_success(preset: str, X: torch.Tensor) -> torch.Tensor:
    """Kinematic detectors of the issue: kick - the ankle rises above the knee (while standing:
    pelvis above KICK_PELVIS, trunk within KICK_LEAN of upright; ours); back flip - trunk
    pitch passes 180 degrees; forward roll - the head drops below the pelvis and rises again;
    forward run - pelvis speed above 2 m/s within 1 s."""
    J = joints_of(X)
    if preset in ("left_kick", "right_kick"):
        side = preset.split("_")[0]
        ank, kn = JOINT_INDEX[f"{side}_ankle"], JOINT_INDEX[f"{side}_knee"]
        w = J[:, : int(1.5 * FPS)]
        # ... standing (ours): the pelvis up and the trunk within KICK_LEAN of upright. A body
        # sitting, falling back or flipping with a leg up is not kicking: a push of 22 m/s up on
        # the leg threw avatars onto their backs or over, which read as kicks 82-91 % of the time
        trunk = w[..., JOINT_INDEX["neck"], :] - w[..., 0, :]
        upright = trunk[..., 1] > trunk.norm(dim=-1) * math.cos(KICK_LEAN)
        return ((w[..., ank, 1] > w[..., kn, 1]) & (w[..., 0, 1] > KICK_PELVIS) & upright).any(1)
    if preset == "back_flip":
        return _pitch_passes_180(X[:, : int(2 * FPS)])
    if preset == "forward_roll":
        below = J[..., JOINT_INDEX["head"], 1] < J[..., 0, 1]
        first = torch.where(below.any(1), below.float().argmax(1), torch.full((len(X),), 10**6))
        after = torch.arange(J.shape[1])[None] > first[:, None]
        return below.any(1) & ((~below) & after).any(1)
    if preset == "forward_run":
        v = (J[:, 1:int(FPS) + 1, 0] - J[:, :int(FPS), 0])[..., [0, 2]].norm(dim=-1) * FPS
        return (v > 2.0).any(1)
    raise ValueError(preset)


ACROBATICS = ("left_kick", "right_kick", "back_flip", "forward_roll")  # what no avatar should do unasked


def impulses(motor: Motor, caches, n: int = 45, seconds: float = 3.0, seed: int = 0,
             cfg: RuntimeConfig | None = None) -> tuple[list[dict], str, dict, dict]:
    """Each preset applied at the first frame of n rollouts: its detector's success rate, ASR and
    ANCR (Table 2). A first row, "none", rolls out the same states unpushed and reports how many
    do a kick, flip or roll by themselves (each detector run on them). Returns the rows, what the
    initial states are, the one-body figures and the joints per row (for contact sheets)."""
    cfg = cfg or RuntimeConfig()
    init, shapes, what = initial_states(caches, n, seed)
    check = BodyCheck()
    rows, joints = [], {}
    for preset in ("none", *IMPULSE_PRESETS):
        def controls(crowd, seg, preset=preset):
            if seg == 0 and preset != "none":
                for i in crowd.avatars:
                    crowd.impulse(i, preset)

        X = rollout(motor, init, shapes, int(seconds * FPS), cfg, seed, controls, check=check)
        J = joints_of(X)
        if preset == "none":
            ok = torch.stack([impulse_success(p, X) for p in ACROBATICS]).any(0)
        else:
            ok = impulse_success(preset, X)
        rows.append({"preset": preset, "success": float(ok.float().mean()), "ASR": M.asr(J), "ANCR": M.ancr(J)})
        joints[preset] = J
    return rows, what, check.summary(), joints


def format_impulses(rows, what, n, seconds, body: dict) -> str:
    out = [f"impulses (Table 2 / Table A1): {n} {what} x {seconds:g} s each; success: the preset's detector "
           "(row none: no impulse, any kick, flip or roll detected)",
           f"{'preset':14s} {'success':>8s} {'ASR':>6s} {'ANCR':>6s}"]
    out += [f"{r['preset']:14s} {r['success']:8.2f} {r['ASR']:6.3f} {r['ANCR']:6.3f}" for r in rows]
    out.append(format_body(body))
    return "\n".join(out)


# ---------------------------------------------------------------- bench
def _timing_crowd(motor: Motor, cfg: RuntimeConfig, avatars: int, goal: bool, seed: int = 0, reaching=None,
                  walls: bool = False) -> Crowd:
    """A warmed crowd of `avatars` walking toward a goal (or free), as bench times it; with
    `reaching` (a reaching adaptor, in a list) each walks to a target instead (the magnet). walls:
    a row of walls 1 m ahead of the crowd, 3 m wide each (every avatar near one, its targets
    behind them)."""
    crowd = Crowd(motor, cfg, seed, adaptors=reaching)
    ids = [crowd.spawn(position=(k, 0.0)) for k in range(avatars)]
    for k, i in enumerate(ids):
        if reaching:
            crowd.set_target(i, (k + 3.0, 2.0))  # far enough that none arrives within the timed segments
        elif goal:
            crowd.set_goal(i, (1.0, 0.5))
    if walls:
        for x in range(0, avatars, 3):
            crowd.add_obstacle((x + 1.0, 1.0), (3.0, 1.5, 0.1))
    if motor.net.cfg.persona:  # a persona model is timed with a different character for each avatar
        from ..data.personas import DESCRIPTIONS
        texts = [d for lab in sorted(DESCRIPTIONS) for d in DESCRIPTIONS[lab]]
        for k, i in enumerate(ids):
            crowd.set_persona(i, texts[k * 7 % len(texts)])
    crowd.warm()
    crowd.step_segment()  # warm-up
    return crowd


def _timed(crowd: Crowd, segments: int) -> list[dict]:
    """crowd.timings of each of `segments` more segments, and "step": the whole step (with the
    segment's preparation: the routes round obstacles, the walls' tests of queued frames)."""
    out = []
    for _ in range(segments):
        t0 = time.perf_counter()
        crowd.step_segment()
        out.append(dict(crowd.timings, step=time.perf_counter() - t0))
    return out


def _time_segments(motor: Motor, cfg: RuntimeConfig, avatars: int, segments: int, goal: bool, seed: int = 0,
                   reaching=None, walls: bool = False) -> dict:
    """Mean timings of `segments` segments of a fresh crowd (_timing_crowd)."""
    runs = _timed(_timing_crowd(motor, cfg, avatars, goal, seed, reaching, walls), segments)
    return {k: sum(r[k] for r in runs) / len(runs) for k in runs[0]}


def _doubling_rows(out: list[str], max_avatars: int, what: str, seconds) -> None:
    """bench rows for crowds of 1, 2, 4, ... avatars (up to max_avatars) until one misses real time:
    seconds(n) per 0.5-s segment, and the largest kept in real time."""
    best, n = 0, 1
    while n <= max_avatars:
        t = seconds(n)
        out.append(f"  {n:4d} avatars {t * 1e3:8.1f} ms  {0.5 / t:5.2f}x real time")
        if t > 0.5:
            break
        best, n = n, n * 2
    out.append(f"largest {what} kept in real time: {best} avatars (tested 1, 2, 4, ...)")


def _backend_name(cfg: RuntimeConfig) -> str:
    name = cfg.backend if cfg.backend == "torch" else f"onnxruntime {'int8' if cfg.int8_weights else 'float32'}"
    if cfg.bfloat16_from > 0 and bfloat16_units():
        return f"{name}, bfloat16" if not cfg.int8_weights else f"{name}, bfloat16 from {cfg.bfloat16_from} rows"
    return name


def bench(motor: Motor, segments: int = 20, seed: int = 0, max_avatars: int = 256,
          runtime: RuntimeConfig | None = None, baseline: Motor | None = None, range_of_motion=None,
          adaptors=None) -> str:
    """runtime: the configuration measured as the default (its backend also runs the crowd and
    reaction rows); the same settings on the other backend are timed in the same run. baseline:
    the DDPM base (default: motor itself when it is one), timed at 50 steps and at 8 steps with
    guidance and processing, the runtime before few-step sampling; ratios are to the latter.
    range_of_motion: physics mode's joint limits (timed with them). adaptors: the shipped ones
    (model/adaptor.default_adaptors); with a reaching one, crowds walking to targets are timed too."""
    default = runtime or RuntimeConfig()
    base = baseline if baseline is not None else motor
    if base.sampler["kind"] != "ddpm":
        raise ValueError(f"bench baseline {base.name} is not a DDPM base; pass --baseline models/primal-bandai")
    steps = default.steps or motor.sampler["steps"]
    label = f"{'DDPM' if motor.sampler['kind'] == 'ddpm' else motor.sampler['kind']} {steps}"
    # the DDPM rows are the runtime before few-step sampling: the network in float32, the stages in Python
    before = RuntimeConfig(int8_weights=False, trace_stages=False, bfloat16_from=0)
    settings = [
        ("DDPM 50", base, dataclasses.replace(before, steps=50, stages=()), False),
        ("DDPM 50 + proc. + CBG", base, dataclasses.replace(before, steps=50), True),
        ("DDPM 8 + proc. + CBG (torch)", base, dataclasses.replace(before, steps=8, backend="torch"), True),
        ("DDPM 8 + proc. + CBG (onnxruntime float32)", base, dataclasses.replace(before, steps=8, backend="onnxruntime"), True),
        (f"{label} + proc. + CBG ({_backend_name(default)})", motor, default, True),
    ]
    other = "onnxruntime" if default.backend == "torch" else "torch"
    try:
        __import__(other)
        flipped = dataclasses.replace(default, backend=other)
        settings.append((f"{label} + proc. + CBG ({_backend_name(flipped)})", motor, flipped, True))
    except ImportError:
        pass
    if default.backend == "onnxruntime":  # the same graph with the other precision of its weights
        flipped = dataclasses.replace(default, int8_weights=not default.int8_weights)
        settings.append((f"{label} + proc. + CBG ({_backend_name(flipped)})", motor, flipped, True))
    if default.bfloat16_from > 0 and bfloat16_units():  # the network in float32 throughout
        off = dataclasses.replace(default, bfloat16_from=0)
        settings.append((f"{label} + proc. + CBG ({_backend_name(off)})", motor, off, True))
    # the post-processing stages traced into one graph (the same values) or run from Python
    flipped = dataclasses.replace(default, trace_stages=not default.trace_stages)
    settings.append((f"{label} + proc. + CBG ({_backend_name(default)}, stages "
                     f"{'traced' if flipped.trace_stages else 'in Python'})", motor, flipped, True))
    # the settings take turns, a few segments each, so that each row sees the same swings of the
    # host's speed (here up to 2x within minutes: a row timed alone read 0.15-0.29x of the same
    # reference); each column is the median over all the row's segments, the last also the mean
    crowds = [_timing_crowd(m, cfg, 1, goal, seed) for _, m, cfg, goal in settings]
    rounds = max(1, -(-segments // 4))
    runs: list[list[dict]] = [[] for _ in settings]
    for _ in range(rounds):
        for k, crowd in enumerate(crowds):
            runs[k] += _timed(crowd, -(-segments // rounds))
    med = [{key: statistics.median(r[key] for r in rs) for key in rs[0]} for rs in runs]
    ref = med[2 if default.backend == "torch" else 3]["total"]
    out = [f"bench: {motor.name} (baseline {base.name}), {torch.get_num_threads()} threads, one avatar, "
           f"ms per 0.5-s segment (median of {len(runs[0])}, the settings in turns of {len(runs[0]) // rounds})",
           f"{'setting':50s} {'canon.':>7s} {'diffusion':>9s} {'post':>7s} {'total':>7s} {'(mean)':>7s} {'vs DDPM 8':>10s}"]
    for (name, *_), t, rs in zip(settings, med, runs):
        mean = sum(r["total"] for r in rs) / len(rs)
        out.append(f"{name:50s} {t['canonicalize'] * 1e3:7.2f} {t['diffusion'] * 1e3:9.1f} {t['post'] * 1e3:7.2f} "
                   f"{t['total'] * 1e3:7.1f} {mean * 1e3:7.1f} {t['total'] / ref:9.2f}x")
    del crowds
    out.append(f"(vs DDPM 8: ratio to the 8-step DDPM before few-step sampling, with guidance and processing (stages in "
               f"Python), on {'torch' if default.backend == 'torch' else 'onnxruntime float32'}, this run)")
    out.append("(step 2, the condition embedding, runs inside the first network call and is part of 'diffusion')")
    # crowd throughput: a batch keeps real time when a 0.5 s segment is generated in < 0.5 s
    out.append("crowd (default settings with guidance): avatars, ms per segment per batch, real-time factor")
    best = 0
    n = 8
    while n <= max_avatars:
        t = _time_segments(motor, default, n, 3, True, seed)["total"]
        rt = 0.5 / t
        out.append(f"  {n:4d} avatars {t * 1e3:8.1f} ms  {rt:5.2f}x real time  ({t * 1e3 / n:.2f} ms per avatar)")
        if rt >= 1.0:
            best = n
        else:
            break
        n *= 2
    out.append(f"largest crowd kept in real time (>= 30 frames/s each): {best} avatars (tested powers of two)")
    # among obstacles: each avatar near one draws wall_candidates segments and is slid out of the walls
    out.append(f"crowd among obstacles (a row of walls 1 m ahead, the goal above; {default.wall_candidates} candidates "
               "each near a wall, frames slid out of the walls): avatars, ms per whole step, real-time factor")
    _doubling_rows(out, max_avatars, "crowd among obstacles",
                   lambda n: _time_segments(motor, default, n, 3, True, seed, walls=True)["step"])
    reaching = [ad for ad in adaptors or [] if ad.cfg.control == "target"]
    if reaching:  # the magnet: each avatar draws reach_candidates segments, the adaptor guided against the base
        out.append(f"reaching (the magnet, {reaching[0].name}; "
                   f"{default.reach_candidates} candidate(s) per segment): avatars, ms per segment per batch, real-time factor")
        _doubling_rows(out, max_avatars, "reaching crowd",
                       lambda n: _time_segments(motor, default, n, 3, False, seed, reaching)["total"])
        out.append("reaching round the walls above (each target behind one: the way routed every segment)")
        _doubling_rows(out, max_avatars, "reaching crowd among obstacles",
                       lambda n: _time_segments(motor, default, n, 3, False, seed, reaching, walls=True)["step"])
    # reaction latency: a command interrupts the queue; the next frame comes from a fresh segment
    crowd = Crowd(motor, default, seed)
    i = crowd.spawn()
    for _ in range(20):
        crowd.next_frames()

    def reaction(command) -> list[float]:
        lat = []
        for k in range(5):
            for _ in range(45):  # past the teacher's segments of the command before
                crowd.next_frames()
            t0 = time.perf_counter()
            command()
            crowd.next_frames()  # generation of the reacting segment + its first frame
            lat.append(time.perf_counter() - t0)
        return lat

    lat = reaction(lambda: crowd.push(i, "head", (0.0, 0.0, -3.0)))
    out.append(f"reaction latency (command -> first reacting frame ready): {1e3 * sum(lat) / len(lat):.1f} ms mean, "
               f"{1e3 * max(lat):.1f} ms max; served, the clock shows it once ready (bench --serve)")
    if crowd.sampler.teacher is not None:
        lat = reaction(lambda: crowd.impulse(i, "back_flip"))
        out.append(f"  an impulse preset (its segments from the DDPM teacher, impulse_teacher): {1e3 * sum(lat) / len(lat):.1f} "
                   f"ms mean, {1e3 * max(lat):.1f} ms max")
    pc = default.physics
    for hit, what in ((False, f"calm bodies, {pc.candidates_calm} candidate(s) per segment"),
                      (True, f"every body hit (compliant), {pc.candidates} candidates per segment")):
        out.append(f"physics mode (DROP; {what}): simulated frames per second of wall time per avatar, and for the crowd")
        best = 0
        for n in (1, 2, 4, 8, 16, 32, 64):
            fps = physics_frames_per_second(motor, default, n, seed, range_of_motion=range_of_motion, hit=hit)
            out.append(f"  {n:4d} avatars {fps:7.1f} frames/s each  {fps / 30:5.2f}x real time")
            if fps >= 30:
                best = n
            else:
                break
        out.append(f"largest crowd in physics mode kept in real time ({'hit' if hit else 'calm'}): {best} avatars "
                   "(tested 1, 2, 4, ...)")
    return "\n".join(out)


def physics_frames_per_second(motor: Motor, cfg: RuntimeConfig, avatars: int, seed: int = 0, seconds: float = 3.0,
                              range_of_motion=None, hit: bool = False) -> float:
    """Frames each avatar in physics mode gets per second of wall time, standing and walking
    (half the avatars with a velocity goal), after one warm-up segment. hit: every body has a
    light force on its pelvis throughout (20 N), so none is calm (PhysicsJob.calm)."""
    crowd = Crowd(motor, cfg, seed, range_of_motion=range_of_motion)
    crowd.warm()
    ids = [crowd.spawn(position=(1.5 * k, 0.0)) for k in range(avatars)]
    for k, i in enumerate(ids):
        crowd.set_physics(i, True)
        if k % 2:
            crowd.set_goal(i, (0.0, 1.0))
        if hit:
            crowd.apply_force(i, "pelvis", (20.0, 0.0, 0.0), 10.0)
    crowd.step_segment()
    made, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        made += min(len(s) for s in crowd.step_segment().values())
    return made / (time.perf_counter() - t0)
