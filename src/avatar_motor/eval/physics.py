"""`avatar-motor eval physics`: DROP's evaluation (§8) made measurable, on the exported body.

Held-out real states (or standing bodies without data) are rolled out in physics mode for 1 s,
perturbed, and watched for 5 s more:
- the push series: a horizontal force on the pelvis held PUSH_SECONDS, 50 to 400 N s, each
  rollout its own direction; balls of 1-5 kg at 5-15 m/s thrown at the chest from 1.5 m;
- per condition: the response (how far the pelvis goes in the second after, beyond where the
  same state's unperturbed rollout goes), rollouts that stay up, that fall (pelvis below
  FALLEN m) and are up again (pelvis above UP m) by the end, the deepest ground penetration,
  skating (ASR) and the root-wrench metric (physics/wrench.py) from the end of the push on;
- the root-wrench metric of real held-out clips, the range real motion shows (DROP Fig. 7);
- energy curves of each term over a pushed run and a hit (DROP Fig. 4);
- the ablations of DROP §8: no prior (kinematic weight 0), no contact, no range of motion; and
  with the soft correction, which the shipped configuration leaves off (PhysicsConfig.correction);
- the environment (DROP §8.2), from standing bodies: a goal velocity followed with and without
  the centre-of-mass velocity energy (Eq. 16); a bar across the walked path, of rising height
  (does the body step over it, stumble, fall), in physics mode and not (the runtime simulates a
  body near a low bar itself); a ground tilted under the standing body; and a
  tilting platform (DROP Fig. 1), the ground turning under it after BEFORE s, rising or falling.
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import torch

from ..body.motion_state import FPS, joints_of, unpack
from ..model.checkpoint import Motor
from ..physics import limits, wrench
from ..body.skeleton import SHAPE_DIM
from ..physics.environment import Box, Environment, Ground
from ..physics.solver import COLLISION_RADIUS, MASS_SHARE, PhysicsConfig
from ..runtime.crowd import Crowd, RuntimeConfig, standing_state
from . import metrics as M
from .control import initial_states
from .realism import RealData, rollout

PUSHES = (50.0, 100.0, 200.0, 300.0, 400.0)  # N s at the pelvis
BALLS = tuple((m, v) for m in (1.0, 3.0, 5.0) for v in (5.0, 10.0, 15.0))  # kg, m/s at the chest
PUSH_SECONDS = 0.1  # a push is a force held this long (400 N s: 4,000 N)
BEFORE, AFTER = 1.0, 5.0  # seconds before the perturbation and watched after it
FALLEN, UP = 0.45, 0.7  # pelvis heights (m): below, the body is down; above at the end, up again
THROW_FROM = 1.5  # m from the chest, horizontally
CHEST = 9  # spine3
CORRECTION = 1e-5  # the ablation with DROP's soft correction (off in the shipped config: PhysicsConfig)
GOAL_SPEED = 1.2  # m/s: the walk of the environment rows
BARS = (0.1, 0.2, 0.3, 0.45)  # m: heights of the bar across the path (15 cm deep), 1.5 m ahead
STEP_OVER_BARS = (0.1, 0.2, 0.3)  # m: the same for bodies not in physics mode (RuntimeConfig.step_over)
BAR_AHEAD = 1.5
TILTS = (5.0, 10.0, 20.0)  # degrees, about the world X axis under the bodies
# a tilting platform: degrees about the world X axis, reached in that many seconds, about a
# pivot line PLATFORM_PIVOT m ahead of the bodies (+: the ground under them rises, -: it falls away)
PLATFORMS = ((10.0, 1.0), (20.0, 2.0), (20.0, 1.0), (-20.0, 1.0))
PLATFORM_PIVOT = 2.0
SPACING = 3.0  # m between the bodies of the environment rows (they do not meet each other)


def _direction(g: torch.Generator) -> torch.Tensor:
    a = float(torch.rand(1, generator=g)) * 2 * math.pi
    return torch.tensor([math.cos(a), 0.0, math.sin(a)])


def perturbation(kind: str, amount: float, speed: float = 0.0, seed: int = 0, gravity: float = PhysicsConfig.gravity):
    """controls(crowd, segment) for `rollout`: at the first segment boundary after BEFORE s, a push
    of `amount` N s at the pelvis, or a ball of `amount` kg at `speed` m/s at the chest, each
    avatar from its own random direction. Records each avatar's frame of the perturbation in
    controls.at."""
    g = torch.Generator().manual_seed(seed)
    dirs: dict[int, torch.Tensor] = {}

    def controls(crowd, seg):
        for i, a in crowd.avatars.items():
            if i in controls.at or a.frame < BEFORE * FPS:
                continue
            d = dirs.setdefault(i, _direction(g))
            controls.at[i] = a.frame
            if kind == "push":
                crowd.apply_force(i, "pelvis", (d * amount / PUSH_SECONDS).tolist(), PUSH_SECONDS)
            else:
                chest = joints_of(a.state.double())[CHEST].float()
                t = THROW_FROM / speed
                v = -d * speed + torch.tensor([0.0, gravity * t / 2, 0.0])  # arcs onto the chest
                crowd.throw(i, (chest + d * THROW_FROM).tolist(), v.tolist(), mass=amount)

    controls.at = {}
    return controls


def root_wrench_series(J: torch.Tensor, phys: PhysicsConfig) -> np.ndarray:
    """The root-wrench metric in body weights at each frame t >= 1 of joints J (T, 22, 3): the
    force no ground contact at frame t can give for the motion into frame t + 1
    (wrench.root_wrench), for a body of phys.mass under phys.gravity with phys.friction."""
    x = J.double().numpy()
    m = (MASS_SHARE.double() * phys.mass).numpy()
    out = []
    for t in range(1, len(x) - 1):
        v = (x[t] - x[t - 1]) * FPS
        out.append(wrench.root_wrench(x[t + 1], x[t], v, m, wrench.contacts(x[t]), phys.gravity, phys.friction)[0])
    return np.array(out) / (phys.mass * phys.gravity)


def joint_limit_excess(X: torch.Tensor, rom) -> torch.Tensor:
    """Degrees (B, T, 21) by which each joint's rotation lies outside the range of motion."""
    return torch.rad2deg(limits.excess(unpack(X.double()).local_rot, rom).clamp(min=0.0))


def measure(X: torch.Tensor, at: list[int], base: torch.Tensor | None, phys: PhysicsConfig, rom) -> dict:
    """The figures of one condition: X (B, T, 267) exported, perturbed at frames `at` (B,), base
    the same states unperturbed (None: this is the unperturbed row); phys: the simulated body's
    mass, gravity and friction (the root-wrench metric's)."""
    J = joints_of(X)
    pel = J[..., 0, :]
    base_pel = None if base is None else joints_of(base)[:, :, 0]
    B, T = J.shape[:2]
    resp, fell, got_up, ghosts = [], [], [], []
    for b in range(B):
        p = at[b]
        end = min(p + int(FPS), T - 1)
        move = pel[b, end, [0, 2]] - pel[b, p, [0, 2]]
        if base_pel is not None:
            move = move - (base_pel[b, end, [0, 2]] - base_pel[b, p, [0, 2]])
        resp.append(float(move.norm()))
        down = bool((pel[b, p:, 1] < FALLEN).any())
        fell.append(down)
        got_up.append(down and bool((pel[b, -int(0.5 * FPS):, 1] > UP).all()))
        ghosts.append(root_wrench_series(J[b, p + int(PUSH_SECONDS * FPS) + 3:], phys))
    g = np.concatenate(ghosts)
    after = torch.cat([J[b, at[b]:] for b in range(B)])
    row = {"response_m": float(np.mean(resp)), "stayed_up": 1.0 - float(np.mean(fell)),
           "fell_and_got_up": float(np.mean(got_up)), "fell_stayed_down": float(np.mean(fell)) - float(np.mean(got_up)),
           "penetration_cm": 100 * max(0.0, -float(after[..., 1].min())),
           "ASR": M.asr(torch.stack([J[b, at[b]:at[b] + T - max(at)] for b in range(B)])),
           "ghost_median": float(np.median(g)), "ghost_p95": float(np.percentile(g, 95))}
    if rom is not None:
        ex = torch.cat([joint_limit_excess(X[b:b + 1, at[b]:], rom).flatten() for b in range(B)])
        row["limit_excess_p99_deg"] = float(torch.quantile(ex, 0.99))
        row["limit_excess_max_deg"] = float(ex.max())
    return row


def real_wrench(caches, n: int, seconds: float, phys: PhysicsConfig, seed: int) -> dict:
    """The root-wrench metric of held-out real clips (on the average body): its range in real motion."""
    real = RealData.load(caches)
    W = real.windows(seconds)
    W = W[torch.randperm(len(W), generator=torch.Generator().manual_seed(seed))[:n]]
    g = np.concatenate([root_wrench_series(w, phys) for w in W])
    return {"ghost_median": float(np.median(g)), "ghost_p95": float(np.percentile(g, 95)), "windows": len(W)}


def energy_run(motor: Motor, init, shapes, cfg: RuntimeConfig, seed: int, rom, kind: str, amount: float,
               speed: float = 0.0) -> tuple[list[dict], int]:
    """One avatar perturbed as in `perturbation`: each frame's energies (solver.energies) and the
    frame of the perturbation."""
    crowds: list = []
    controls = perturbation(kind, amount, speed, seed, cfg.physics.gravity)

    def traced(crowd, seg):
        if crowd.trace is None:
            crowd.trace = {}
        controls(crowd, seg)

    rollout(motor, init[:1], shapes[:1], int((BEFORE + AFTER) * FPS), cfg, seed, traced, physics=True,
            range_of_motion=rom, crowd_out=crowds)
    (trace,) = crowds[0].trace.values()
    return trace, controls.at[0]


def physics_eval(motor: Motor, caches, n: int = 16, seed: int = 0, cfg: RuntimeConfig | None = None, rom=None,
                 png: str | Path | None = None, progress=print) -> dict:
    cfg = cfg or RuntimeConfig()
    init, shapes, what = initial_states(caches, n, seed)
    phys = cfg.physics
    frames = int((BEFORE + AFTER) * FPS)

    def run(controls=None, physics_cfg=None, range_of_motion=rom):
        c = cfg if physics_cfg is None else dataclasses.replace(cfg, physics=physics_cfg)
        return rollout(motor, init, shapes, frames, c, seed, controls, physics=True, range_of_motion=range_of_motion)

    out = {"what": what, "n": n, "rows": [], "ablations": []}
    base = run()
    start = [int(BEFORE * FPS)] * n
    out["rows"].append({"condition": "none", **measure(base, start, None, phys, rom)})
    progress(f"unperturbed: {out['rows'][-1]}")
    conditions = [("push", j, 0.0, f"push {j:g} N s") for j in PUSHES]
    conditions += [("ball", m, v, f"ball {m:g} kg {v:g} m/s") for m, v in BALLS]
    for kind, amount, speed, name in conditions:
        ctl = perturbation(kind, amount, speed, seed, phys.gravity)
        X = run(ctl)
        out["rows"].append({"condition": name, "kind": kind, "amount": amount, "speed": speed,
                            **measure(X, [ctl.at[i] for i in sorted(ctl.at)], base, phys, rom)})
        progress(f"{name}: {out['rows'][-1]}")
    if caches:
        out["real"] = real_wrench(caches, n, BEFORE + AFTER, phys, seed)
    ablations = [("full system", None, rom), ("no prior (kinematic 0)", dataclasses.replace(cfg.physics, kinematic=0.0, kinematic_calm=0.0), rom),
                 ("no contact", dataclasses.replace(cfg.physics, contact=0.0), rom), ("no range of motion", None, None),
                 ("soft correction", dataclasses.replace(cfg.physics, correction=CORRECTION), rom)]
    for name, pc, r in ablations:
        for kind, amount, speed, cond in (("none", 0.0, 0.0, "unperturbed"), ("push", 200.0, 0.0, "push 200 N s")):
            if name == "full system":
                src = out["rows"][0] if kind == "none" else next(x for x in out["rows"] if x["condition"] == cond)
                row = dict(src)
            else:
                ctl = perturbation(kind, amount, speed, seed, phys.gravity) if kind != "none" else None
                X = run(ctl, pc, r)
                at = [ctl.at[i] for i in sorted(ctl.at)] if ctl else start
                row = measure(X, at, None if ctl is None else base, phys, rom)
            out["ablations"].append({"ablation": name, "condition": cond, **row})
            progress(f"ablation {name}, {cond}: {out['ablations'][-1]}")
    out["energies"] = {}
    for kind, amount, speed, name in (("push", 200.0, 0.0, "push 200 N s"), ("ball", 3.0, 10.0, "ball 3 kg 10 m/s")):
        trace, at = energy_run(motor, init, shapes, cfg, seed, rom, kind, amount, speed)
        out["energies"][name] = {"at": at, "trace": trace}
    if png:
        plot(out, png)
    return out


def _standing_run(motor: Motor, n: int, seconds: float, cfg: RuntimeConfig, seed: int, rom, env: Environment,
                  goal: tuple | None, platform: tuple | None = None, grounds: list | None = None,
                  physics: bool = True) -> torch.Tensor:
    """n average bodies standing in a row along X (SPACING apart, facing +Z) in physics mode in the
    world `env`, given a goal velocity after BEFORE s, or the ground turned (platform: Crowd.set_ground's
    tilt, pivot, seconds) then; (n, T, 22, 3) joints of the exported body. grounds: a list to which
    the ground of each frame is appended. physics False: the model moves them alone (but where the
    runtime simulates them itself: RuntimeConfig.step_over)."""
    crowd = Crowd(motor, cfg, seed, range_of_motion=rom)
    crowd.set_environment(env)
    ids = [crowd.spawn(standing_state(None, (SPACING * k, 0.0)), torch.zeros(SHAPE_DIM)) for k in range(n)]
    for i in ids:
        crowd.set_physics(i, physics)
    frames = []
    for f in range(int(seconds * FPS)):
        if f == int(BEFORE * FPS) and goal is not None:
            for i in ids:
                crowd.set_goal(i, goal)
        if f == int(BEFORE * FPS) and platform is not None:
            crowd.set_ground(*platform)
        shown = crowd.next_frames()
        if grounds is not None:
            grounds.append(crowd.ground_at(crowd.clock))
        frames.append(torch.stack([shown[i] for i in ids]))
    return joints_of(torch.stack(frames, 1).double())


def _up_figures(pel_y: torch.Tensor) -> dict:
    fell = (pel_y < FALLEN).any(1)
    got_up = fell & (pel_y[:, -int(0.5 * FPS):] > UP).all(1)
    return {"stayed_up": 1.0 - float(fell.float().mean()), "fell_and_got_up": float(got_up.float().mean()),
            "stumbled": float((pel_y < UP).any(1).float().mean())}


def environment_eval(motor: Motor, n: int = 16, seed: int = 0, cfg: RuntimeConfig | None = None, rom=None,
                     progress=print) -> dict:
    """The environment rows (module docstring): each a row of figures."""
    cfg = cfg or RuntimeConfig()
    seconds = BEFORE + AFTER
    out = {"n": n, "goal": [], "bars": [], "tilts": []}
    settle = int((BEFORE + 2.0) * FPS)  # the walk measured after 2 s of it
    for name, w in (("without E_com", 0.0), ("with E_com", cfg.physics.com_velocity)):
        c = dataclasses.replace(cfg, physics=dataclasses.replace(cfg.physics, com_velocity=w))
        J = _standing_run(motor, n, seconds, c, seed, rom, Environment(), (0.0, GOAL_SPEED))
        v = (J[:, settle + 1:, 0] - J[:, settle:-1, 0]) * FPS  # (n, T, 3) pelvis velocity
        speed = v[..., 2].mean(1)
        out["goal"].append({"condition": f"goal {GOAL_SPEED:g} m/s, {name}", "weight": w,
                            "speed_error": float((speed - GOAL_SPEED).abs().mean()),
                            "sideways": float(v[..., 0].mean(1).abs().mean()), **_up_figures(J[..., 0, 1])})
        progress(f"{out['goal'][-1]}")
    for h, physics in [(h, True) for h in BARS] + [(h, False) for h in STEP_OVER_BARS]:
        boxes = tuple(Box((SPACING * k, BAR_AHEAD), (2.0, h, 0.15)) for k in range(n))
        J = _standing_run(motor, n, seconds, cfg, seed, rom, Environment(boxes=boxes), (0.0, GOAL_SPEED), physics=physics)
        depth = torch.zeros(())
        for k, b in enumerate(boxes):
            q, e, _, _ = b.local(J[k], COLLISION_RADIUS)
            depth = torch.maximum(depth, (e - q.abs()).amin(-1).max())
        crossed = J[:, -1, 0, 2] > BAR_AHEAD + 0.5
        out["bars"].append({"condition": f"bar {100 * h:g} cm high" + ("" if physics else ", physics off"),
                            "height": h, "physics": physics, "crossed": float(crossed.float().mean()),
                            "penetration_cm": 100 * max(0.0, float(depth)), **_up_figures(J[..., 0, 1])})
        progress(f"{out['bars'][-1]}")
    for tilt in TILTS:
        g = Ground((tilt, 0.0))
        J = _standing_run(motor, n, seconds, cfg, seed, rom, Environment(g), None)
        above = g.height(J)  # joint centres above the plane
        drift = J[:, -1, 0] - J[:, int(BEFORE * FPS), 0]
        out["tilts"].append({"condition": f"ground tilted {tilt:g} deg", "tilt": tilt,
                             "penetration_cm": 100 * max(0.0, -float(above.min())),
                             "downhill_m": float(drift[:, 2].mean()), **_up_figures(J[..., 0, 1] - g.height_below(J[..., 0, [0, 2]]))})
        progress(f"{out['tilts'][-1]}")
    out["platforms"] = []
    for tilt, secs in PLATFORMS:
        grounds = []
        # pivot PLATFORM_PIVOT ahead: a positive tilt (about +X) lifts the ground behind the pivot line
        J = _standing_run(motor, n, seconds, cfg, seed, rom, Environment(), None,
                          ((tilt, 0.0), (0.0, PLATFORM_PIVOT), secs), grounds)
        above = torch.stack([g.height(J[:, t]) for t, g in enumerate(grounds)], 1)  # (n, T, 22)
        under = torch.stack([g.height_below(J[:, t, 0, [0, 2]]) for t, g in enumerate(grounds)], 1)  # (n, T)
        t0 = int(BEFORE * FPS)
        drift = J[:, -1, 0] - J[:, t0, 0]
        out["platforms"].append({"condition": f"tilting to {tilt:g} deg in {secs:g} s", "tilt": tilt, "seconds": secs,
                                 "ground_moved_m": float(under[:, -1].mean() - under[:, t0].mean()),
                                 "penetration_cm": 100 * max(0.0, -float(above.min())),
                                 "moved_m": float(drift[:, [0, 2]].norm(dim=-1).mean()),
                                 **_up_figures(J[..., 0, 1] - under)})
        progress(f"{out['platforms'][-1]}")
    return out


def format_environment(r: dict) -> str:
    lines = [f"environment (DROP 8.2): {r['n']} standing average bodies in physics mode (but 'physics off'), "
             f"{AFTER:g} s after {BEFORE:g} s",
             f"{'direction following':30s} {'speed err':>9s} {'sideways':>8s} {'up':>5s} {'stumbled':>8s}"]
    lines += [f"{x['condition']:30s} {x['speed_error']:9.2f} {x['sideways']:8.2f} {x['stayed_up']:5.2f} {x['stumbled']:8.2f}"
              for x in r["goal"]]
    lines.append(f"{'bar across the path':30s} {'crossed':>9s} {'pen. cm':>8s} {'up':>5s} {'stumbled':>8s} {'got up':>6s}")
    lines += [f"{x['condition']:30s} {x['crossed']:9.2f} {x['penetration_cm']:8.1f} {x['stayed_up']:5.2f} "
              f"{x['stumbled']:8.2f} {x['fell_and_got_up']:6.2f}" for x in r["bars"]]
    lines.append(f"{'tilted ground, standing':30s} {'downhill':>9s} {'pen. cm':>8s} {'up':>5s} {'stumbled':>8s}")
    lines += [f"{x['condition']:30s} {x['downhill_m']:9.2f} {x['penetration_cm']:8.1f} {x['stayed_up']:5.2f} "
              f"{x['stumbled']:8.2f}" for x in r["tilts"]]
    if r.get("platforms"):
        lines.append(f"{'tilting platform, standing':30s} {'ground m':>9s} {'pen. cm':>8s} {'up':>5s} {'stumbled':>8s} "
                     f"{'got up':>6s} {'moved m':>7s}")
        lines += [f"{x['condition']:30s} {x['ground_moved_m']:9.2f} {x['penetration_cm']:8.1f} {x['stayed_up']:5.2f} "
                  f"{x['stumbled']:8.2f} {x['fell_and_got_up']:6.2f} {x['moved_m']:7.2f}" for x in r["platforms"]]
    return "\n".join(lines)


def format_physics(r: dict) -> str:
    lines = [f"physics mode (DROP): {r['n']} {r['what']}, {BEFORE:g} s, then perturbed and watched {AFTER:g} s; exported body",
             "response: pelvis travel in the second after, beyond the unperturbed rollout's; up: never below "
             f"{FALLEN} m; got up: fell and above {UP} m for the last 0.5 s; ghost: root-wrench metric from the end of "
             "the push on, in body weights (median / 95th percentile)",
             f"{'condition':22s} {'response m':>10s} {'up':>5s} {'got up':>6s} {'down':>5s} {'pen. cm':>7s} {'ASR':>6s} "
             f"{'ghost':>11s}" + (f" {'limit p99/max deg':>18s}" if "limit_excess_max_deg" in r["rows"][0] else "")]

    def line(name, x):
        s = (f"{name:22s} {x['response_m']:10.2f} {x['stayed_up']:5.2f} {x['fell_and_got_up']:6.2f} "
             f"{x['fell_stayed_down']:5.2f} {x['penetration_cm']:7.1f} {x['ASR']:6.3f} "
             f"{x['ghost_median']:5.2f}/{x['ghost_p95']:5.2f}")
        if "limit_excess_max_deg" in x:
            s += f" {x['limit_excess_p99_deg']:8.1f}/{x['limit_excess_max_deg']:8.1f}"
        return s

    lines += [line(x["condition"], x) for x in r["rows"]]
    if "real" in r:
        lines.append(f"real held-out motion ({r['real']['windows']} windows): ghost {r['real']['ghost_median']:.2f} / "
                     f"{r['real']['ghost_p95']:.2f} body weights")
    lines.append("ablations (DROP §8):")
    lines += [line(f"{x['ablation'][:13]}, {x['condition'][:8]}", x) for x in r["ablations"]]
    return "\n".join(lines)


def plot(r: dict, png: str | Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    for ax, (name, e) in zip(axes[:2], r["energies"].items()):
        t = np.arange(len(e["trace"])) / FPS
        for term in e["trace"][0]:
            ax.plot(t, [max(f[term], 1e-6) for f in e["trace"]], label=term, lw=1)
        ax.axvline(e["at"] / FPS, color="k", ls="--", lw=0.8)
        ax.set_yscale("log")
        ax.set_xlabel("s")
        ax.set_ylabel("energy (J)")
        ax.set_title(f"energy terms, {name} (dashed)")
        ax.legend(fontsize=7)
    ax = axes[2]
    pushes = [x for x in r["rows"] if x.get("kind") == "push"]
    ax.plot([x["amount"] for x in pushes], [x["response_m"] for x in pushes], "o-", label="push at the pelvis (N s)")
    for m in sorted({x["amount"] for x in r["rows"] if x.get("kind") == "ball"}):
        balls = [x for x in r["rows"] if x.get("kind") == "ball" and x["amount"] == m]
        ax.plot([x["amount"] * x["speed"] for x in balls], [x["response_m"] for x in balls], "s--",
                label=f"ball {m:g} kg (momentum, N s)")
    ax.set_xlabel("impulse (N s)")
    ax.set_ylabel("pelvis response in 1 s (m)")
    ax.set_xscale("log")
    ax.set_title("response grows with the push")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)


def save_json(r: dict, path: str | Path) -> None:
    import json
    Path(path).write_text(json.dumps(r, indent=1))
