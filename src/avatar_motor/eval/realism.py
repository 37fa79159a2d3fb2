"""`avatar-motor eval realism`: autoregressive rollouts from held-out initial states with random
body shapes (PRIMAL §5.1.1), measured against the held-out real motion."""
from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from ..body import rotations as rot
from ..body.skeleton import forward_kinematics, rest_offsets
from ..data.cache import MotionCache, is_held_out
from ..data.dataset import SegmentConfig, SegmentDataset
from ..body.motion_state import FPS, SLICES, body_joints, finite_velocities, joints_of, unpack
from ..model.checkpoint import Motor
from ..runtime.crowd import Crowd, RuntimeConfig
from . import metrics as M


@dataclass
class RealData:
    """Held-out clips on the average body: joints (list of (T, 22, 3)) and local rotations."""
    joints: list[torch.Tensor]
    local_rot: list[torch.Tensor]

    @staticmethod
    def load(caches: list[MotionCache], max_clips: int = 200) -> "RealData":
        Js, Rs = [], []
        off = rest_offsets(None, torch.float64)
        for c in caches:
            for i, clip in enumerate(c.clips):
                if not is_held_out(clip["key"]) or len(Js) >= max_clips:
                    continue
                root, q = c.clip(i)
                R = rot.quat_to_matrix(torch.from_numpy(q).double())
                J, _ = forward_kinematics(torch.from_numpy(root).double(), R[:, 0], R[:, 1:], off)
                Js.append(J.float())
                Rs.append(R[:, 1:].float())
        if not Js:
            raise ValueError("no held-out clip in the motion caches; import the Bandai data first")
        return RealData(Js, Rs)

    def windows(self, seconds: float) -> torch.Tensor:
        """Non-overlapping windows (W, T, 22, 3) of real motion."""
        T = int(seconds * FPS)
        out = [J[s:s + T] for J in self.joints for s in range(0, len(J) - T + 1, T)]
        if not out:
            raise ValueError(f"no held-out clip is {seconds:g} s long; evaluate with fewer --seconds")
        return torch.stack(out)


def training_poses(caches: list[MotionCache], n: int, g: torch.Generator, held_out: bool = False) -> torch.Tensor:
    """n local-rotation poses (n, 21, 3, 3) drawn uniformly from the frames of the training clips
    (of the held-out clips with held_out)."""
    clips = [(c, i) for c in caches for i, clip in enumerate(c.clips) if is_held_out(clip["key"]) == held_out]
    if not clips:
        raise ValueError(f"no {'held-out' if held_out else 'training'} clip in the motion caches {[str(c.path) for c in caches]}")
    lengths = torch.tensor([c.clips[i]["frames"] for c, i in clips])
    pick = torch.multinomial(lengths.double(), n, replacement=True, generator=g)
    frames = (torch.rand(n, generator=g) * lengths[pick]).long()
    out = []
    for k, f in zip(pick.tolist(), frames.tolist()):
        c, i = clips[k]
        out.append(torch.from_numpy(c.clip(i)[1][f]).double())
    return rot.quat_to_matrix(torch.stack(out))[:, 1:].float()


class BodyCheck:
    """The one-body figures of the rollouts it is shown: the distance between the joint locations
    the runtime emitted and FK of the rotations it emitted (max and 99th percentile over every
    joint of every frame), and the lowest joint of the exported body."""

    def __init__(self):
        self.dist: list[torch.Tensor] = []
        self.lowest = float("inf")

    def add(self, X: torch.Tensor, J: torch.Tensor) -> None:
        """X (B, T, 267) as emitted; J (B, T, 22, 3) FK of its rotations (`body_joints`)."""
        self.dist.append((joints_of(X).double() - J).norm(dim=-1).flatten().float())
        self.lowest = min(self.lowest, float(J[..., 1].min()))

    def summary(self) -> dict:
        d = torch.cat(self.dist)
        return {"body_mismatch_max_mm": 1000 * float(d.max()),
                "body_mismatch_p99_mm": 1000 * float(torch.quantile(d[torch.randperm(len(d), generator=torch.Generator().manual_seed(0))[:1_000_000]], 0.99)),
                "lowest_joint_m": self.lowest}


def exported(X: torch.Tensor, J: torch.Tensor) -> torch.Tensor:
    """States (B, T, 267) whose joint locations and velocities are those of the exported body J
    (B, T, 22, 3), FK of X's rotations on each shape: what every metric reads."""
    out = X.clone()
    out[..., SLICES["joints"]] = J.reshape(*X.shape[:-1], 66).to(X.dtype)
    out[..., SLICES["velocities"]] = finite_velocities(J).reshape(*X.shape[:-1], 66).to(X.dtype)
    return out


def format_body(r: dict) -> str:
    return (f"one body: joints emitted vs FK of rotations emitted: max {r['body_mismatch_max_mm']:.3f} mm, "
            f"p99 {r['body_mismatch_p99_mm']:.3f} mm (goal <= 1 mm); lowest exported joint {100 * r['lowest_joint_m']:+.1f} cm (goal >= -2 cm)")


def rollout(motor: Motor, init: torch.Tensor, shapes: torch.Tensor, frames: int, cfg: RuntimeConfig, seed: int,
            controls=None, adaptor=None, check: BodyCheck | None = None, physics: bool = False,
            range_of_motion=None, crowd_out: list | None = None, joins_out: list | None = None) -> torch.Tensor:
    """Batched autoregressive rollout: (B, 1 + frames, 267) world states of the exported body
    (`exported`), init first. controls(crowd, segment_index) may set goals/impulses/labels before
    each segment; `check` collects the one-body figures of what the runtime emitted. physics:
    every avatar in physics mode (its segments end where the simulation resamples, so avatars
    run on their own segment boundaries); crowd_out: a list the Crowd is appended to; joins_out:
    a list each avatar's join frames are appended to (the index in the result of every segment's
    first frame, from 1: the first segment's join with init)."""
    crowd = Crowd(motor, cfg, seed, adaptor, range_of_motion)
    if crowd_out is not None:
        crowd_out.append(crowd)
    ids = [crowd.spawn(init[k], shapes[k]) for k in range(len(init))]
    for i in ids:
        crowd.set_physics(i, physics)
    made = {i: [init[k][None].float()] for k, i in enumerate(ids)}
    n = 0
    while min(sum(len(s) for s in made[i]) for i in ids) < frames + 1:
        if controls is not None:
            controls(crowd, n)
        out = crowd.step_segment()
        for i in ids:
            made[i].append(out[i])
        n += 1
    X = torch.stack([torch.cat(made[i])[: frames + 1] for i in ids])
    if joins_out is not None:
        for i in ids:
            starts = torch.tensor([len(s) for s in made[i]]).cumsum(0)[:-1]  # after init and each segment
            joins_out.append([int(j) for j in starts if j <= frames])
    J = body_joints(X.double(), rest_offsets(shapes, torch.float64)[:, None])
    if check is not None:
        check.add(X, J)
    return exported(X, J)


def realism(motor: Motor, caches: list[MotionCache], n: int = 64, seconds: float = 8.0, seed: int = 0,
            cfg: RuntimeConfig | None = None, stability_seconds: float = 60.0, stability_n: int = 16,
            sheet: str | Path | None = None, export_dir: str | Path | None = None, progress=print,
            physics: bool = False, range_of_motion=None) -> dict:
    """physics: every avatar in physics mode (DROP) with the joint limits range_of_motion."""
    cfg = cfg or RuntimeConfig()
    sim = {"physics": physics, "range_of_motion": range_of_motion}
    g = torch.Generator().manual_seed(seed)
    held = SegmentDataset(caches, SegmentConfig(frames=15, split="heldout", mirror=False))
    x, shapes = held.sample(n, g)
    init = x[:, 0]
    t0 = time.time()
    check = BodyCheck()
    joins: list[list[int]] = []
    X = rollout(motor, init, shapes, int(seconds * FPS), cfg, seed, check=check, joins_out=joins, **sim)
    gen_time = time.time() - t0
    J = joints_of(X)
    real = RealData.load(caches)
    Jr = real.windows(seconds)
    # pose naturalness: distance to the nearest training pose (and its mirror image: the model is
    # trained with mirroring), generated poses vs held-out real poses. The held-out clips are
    # unseen by the model, so the real value is what a new, real performance scores.
    ref_rot = training_poses(caches, 10000, g)
    ref = M.pose_features(torch.cat((ref_rot, M.mirror_local_rotations(ref_rot))))
    real_rot = torch.cat(real.local_rot)
    real_q = M.pose_features(real_rot[torch.randperm(len(real_rot), generator=g)[:4000]])
    gen_poses = M.pose_features(unpack(X[:, 1:].reshape(-1, X.shape[-1])).local_rot)
    gen_poses = gen_poses[torch.randperm(len(gen_poses), generator=g)[:4000]]
    d_gen = float(M.nn_pose_distance(gen_poses, ref).mean())
    d_real = float(M.nn_pose_distance(real_q, ref).mean())
    res = {
        "n": n, "seconds": seconds, "steps": cfg.steps or motor.sampler["steps"], "sampler": motor.sampler["kind"],
        "physics": physics,
        "ASR": M.asr(J), "ASR_real": M.asr(Jr),
        "ANCR": M.ancr(J), "ANCR_real": M.ancr(Jr),
        "naturalness_ratio": d_gen / d_real, "pose_nn_dist": d_gen, "pose_nn_dist_real": d_real,
        "jitter_ratio": M.jitter(J) / M.jitter(Jr), "jitter": M.jitter(J), "jitter_real": M.jitter(Jr),
        "alive": M.alive_ratio(J), "alive_real": M.alive_ratio(Jr),
        "seconds_per_rollout_batch": gen_time,
    }
    try:  # physics mode may resample every few frames, leaving no window away from a join
        res["join_ratio"] = M.join_jerk(J, joins)
    except ValueError:
        pass
    res.update(check.summary())
    if stability_seconds > 0:
        k = min(stability_n, n)
        Xs = rollout(motor, init[:k], shapes[:k], int(stability_seconds * FPS), cfg, seed + 1, **sim)
        Js = joints_of(Xs)
        pel = Js[..., 0, 1]
        res.update({
            "stability_seconds": stability_seconds, "stability_n": k,
            "stable_no_nan": bool(torch.isfinite(Xs).all()),
            "stable_pelvis_band": [float(pel.min()), float(pel.max())],
            "stable_height_ok": bool(((pel > 0.15) & (pel < 1.6)).all()),
            "frozen_rollouts": int(M.frozen(Js).sum()),
            "alive_last_20s": M.alive_ratio(Js[:, -int(20 * FPS):]),
        })
    if sheet:
        from ..viz import contact_sheet
        contact_sheet([J[k].numpy() for k in range(min(6, n))], sheet, titles=[f"rollout {k}" for k in range(min(6, n))])
    if export_dir:
        from ..io.export import write_motion
        d = Path(export_dir)
        files = []
        for k in range(min(4, n)):
            for ext in ("bvh", "glb"):
                files.append(write_motion(d / f"rollout_{k}.{ext}", X[k], shapes[k]))
        res.update(exported_files(files))
    return res


def exported_files(paths) -> dict:
    """ANCR and the lowest joint of exported BVH and glTF files, read back from the files alone
    (each format's own hierarchy, offsets and rotations): what a user's tool shows."""
    from ..io.bvh import read_bvh
    from ..io.export import BVH_SCALE
    from ..io.gltf import read_glb_joints
    Js = []
    for p in paths:
        if str(p).endswith(".bvh"):
            P, _ = read_bvh(p).global_transforms()
            Js.append(torch.from_numpy(P / BVH_SCALE))
        else:
            Js.append(torch.from_numpy(read_glb_joints(p)[1]))
    return {"exported_files": len(Js), "exported_ANCR": sum(M.ancr(J) * len(J) for J in Js) / sum(len(J) for J in Js),
            "exported_lowest_joint_m": min(float(J[..., 1].min()) for J in Js)}


def format_realism(r: dict) -> str:
    rows = [
        ("ASR (skating, lower is better)", f"{r['ASR']:.3f}", f"{r['ASR_real']:.3f}", "<= 0.05"),
        ("ANCR (non-collision)", f"{r['ANCR']:.3f}", f"{r['ANCR_real']:.3f}", ">= 0.99"),
        ("pose naturalness ratio", f"{r['naturalness_ratio']:.2f}", "1.00", "<= 1.5"),
        ("jitter ratio", f"{r['jitter_ratio']:.2f}", "1.00", "<= 1.5"),
        ("alive ratio", f"{r['alive']:.2f}", f"{r['alive_real']:.2f}", "within 0.15 of real"),
    ]
    if "join_ratio" in r:  # jerk across segment joins over within segments: the seams' roughness
        rows.append(("join roughness (across / within)", f"{r['join_ratio']:.2f}", "1.00", "1 is seamless"))
    out = [f"realism: {r['n']} rollouts x {r['seconds']:.0f} s, {r['steps']} denoising steps ({r.get('sampler', 'ddpm')})"
           + (", physics mode" if r.get("physics") else ""),
           f"{'metric':34s} {'generated':>10s} {'real':>8s}  goal"]
    out += [f"{a:34s} {b:>10s} {c:>8s}  {d}" for a, b, c, d in rows]
    out.append(format_body(r))
    if "exported_files" in r:
        out.append(f"exported files read back ({r['exported_files']} BVH and glTF): ANCR {r['exported_ANCR']:.3f} (goal >= 0.99), "
                   f"lowest joint {100 * r['exported_lowest_joint_m']:+.1f} cm (goal >= -2 cm)")
    if "stability_seconds" in r:
        out.append(f"stability {r['stability_seconds']:.0f} s x {r['stability_n']}: no NaN {r['stable_no_nan']}, "
                   f"pelvis height {r['stable_pelvis_band'][0]:.2f}..{r['stable_pelvis_band'][1]:.2f} m "
                   f"(ok {r['stable_height_ok']}), frozen rollouts {r['frozen_rollouts']}, alive in last 20 s {r['alive_last_20s']:.2f}")
    return "\n".join(out)


def save_json(r: dict, path: str | Path) -> None:
    Path(path).write_text(json.dumps(r, indent=1))

