"""DeepMimic's motion format (io/deepmimic.py) and its import onto the canonical body."""
import json
import subprocess
import sys
import zipfile

import numpy as np
import pytest
import torch

from avatar_motor.body import rotations as rot
from avatar_motor.body.skeleton import JOINT_INDEX, forward_kinematics, rest_offsets
from avatar_motor.data.cache import MotionCache, import_motion
from avatar_motor.data.retarget import retarget
from avatar_motor.io.deepmimic import AXES, DeepMimicError, read_deepmimic

from .fixture_tools import deepmimic_clip


def canonical_joints(r) -> torch.Tensor:
    q = rot.quat_to_matrix(torch.from_numpy(r.quats).double())
    return forward_kinematics(torch.from_numpy(r.root_pos).double(), q[:, 0], q[:, 1:], rest_offsets(None, torch.float64))[0]


def convert(data: bytes):
    b = read_deepmimic(data, "clip.txt")
    return b, retarget(b, unit="m", axes=AXES, ground="source")


def unit(v: torch.Tensor) -> torch.Tensor:
    return v / v.norm(dim=-1, keepdim=True)


@pytest.mark.parametrize("lying", [False, True])
def test_bones_point_where_the_file_says(lying):
    """The file's rotations, composed by hand (w, x, y, z quaternions; knee and elbow angles about
    z; thigh, shin and forearm along -y at rest), give the bone directions; the canonical body
    must point its bones the same way in our axes (DeepMimic +x forward = our +z, +z right = our -x)."""
    data, rots = deepmimic_clip(lying=lying)
    b, r = convert(data)
    assert r.info["skeleton"] == "deepmimic" and r.fps == pytest.approx(30.0, rel=1e-4)
    J = canonical_joints(r)
    A = torch.from_numpy(AXES)
    down = torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64)
    z = lambda a: rot.axis_angle_to_matrix(torch.stack((0 * a, 0 * a, a), -1))
    thigh = rots["root"] @ rots["hip"] @ down
    shin = rots["root"] @ rots["hip"] @ z(rots["knee"]) @ down
    forearm = rots["root"] @ z(rots["elbow"]) @ down
    for (a, c), want in ((("right_hip", "right_knee"), thigh), (("right_knee", "right_ankle"), shin),
                         (("left_elbow", "left_wrist"), forearm)):
        got = unit(J[:, JOINT_INDEX[c]] - J[:, JOINT_INDEX[a]])
        cos = (got * unit(want @ A.T)).sum(-1)
        assert cos.min() > 0.99, (a, c, float(cos.min()))
    # up stays up and the ground is the file's: standing, the toes are FOOT_CLEARANCE-ish above
    # it; lying, the back is on it (no joint below, none floating)
    low = J[..., 1].min(-1).values
    assert low.min() > -0.03 and low.max() < 0.12
    if lying:
        assert J[:, JOINT_INDEX["head"], 1].max() < 0.3  # lying, not stood up by a wrong up axis


def test_frames_of_unequal_duration_are_resampled():
    frames = 10
    dur = [1 / 30] * frames
    dur[4] = 2 / 30  # one long frame: the clip lasts 10 frame times, not 9
    data, _ = deepmimic_clip(frames, durations=dur)
    b = read_deepmimic(data, "uneven.txt")
    assert b.frame_time == pytest.approx(1 / 30, rel=1e-4) and b.num_frames == 11
    even = read_deepmimic(deepmimic_clip(frames)[0], "even.txt")
    assert even.num_frames == frames
    # the long frame's midpoint lies halfway between its two keys
    P, _ = b.global_transforms()
    assert np.allclose(P[5, 0, 1], P[4, 0, 1], atol=1e-6)  # root height is constant in this clip
    assert P[5, 0, 0] == pytest.approx(0.5 * (P[4, 0, 0] + P[6, 0, 0]), abs=1e-6)


@pytest.mark.parametrize("mutate, message", [
    (lambda d: b"not json", "not valid JSON"),
    (lambda d: json.dumps({"Loop": "none"}).encode(), "no 'Frames' list"),
    (lambda d: json.dumps({"Frames": [[0.0] * 20, [0.0] * 20]}).encode(), "frame 0 has 20 values"),
    (lambda d: d.replace(b"0.033333", b"NaN", 1), "NaN or infinite"),
    (lambda d: d.replace(b"0.033333", b"0.0", 1), "lasts 0 s"),
    (lambda d: json.dumps({"Frames": json.loads(d)["Frames"][:1]}).encode(), r"has 1 frame\(s\)"),
    (lambda d: json.dumps({"Frames": [[f[0], f[1], f[2], f[3], 0.0, 0.0, 0.0, 0.0] + f[8:] for f in json.loads(d)["Frames"]]}).encode(),
     "quaternion has norm 0"),
])
def test_bad_files_are_named(mutate, message):
    data, _ = deepmimic_clip(5)
    with pytest.raises(DeepMimicError, match=message) as e:
        read_deepmimic(mutate(data), "bad.txt")
    assert str(e.value).startswith("bad.txt:")


def test_the_wheel_imports_its_humanoid_clips(tmp_path):
    """pybullet's wheel as a user passes it: humanoid3d clips imported and labelled, another
    character's clip skipped with its reason, a text file and a JSON object without frames (an
    agent's settings; the Bandai data's labels beside each BVH) that are no motion passed over."""
    wheel = tmp_path / "pybullet-0.0.0-cp311-none-any.whl"
    with zipfile.ZipFile(wheel, "w") as z:
        z.writestr("pybullet_data/data/motions/humanoid3d_kick.txt", deepmimic_clip()[0])
        z.writestr("pybullet_data/data/motions/humanoid3d_roll.txt", deepmimic_clip(30, lying=True)[0])
        z.writestr("pybullet_data/data/motions/laikago_walk.txt", json.dumps({"Frames": [[0.1] * 20] * 3}))
        z.writestr("pybullet_data/README.txt", "not a motion")
        z.writestr("pybullet_data/data/agents/ct_agent_humanoid_ppo.txt", json.dumps({"AgentType": "PPO"}))
        z.writestr("pybullet/__init__.py", "")
    path, summary = import_motion(wheel, progress=False, workers=1)
    assert path.name == "deepmimic.npz"
    c = MotionCache.load(path)
    assert [cl["labels"] for cl in c.clips] == [{"content": "kick"}, {"content": "roll"}]
    assert [s["key"] for s in summary["skipped"]] == ["pybullet_data/data/motions/laikago_walk.txt"]
    assert "another DeepMimic character" in summary["skipped"][0]["reason"]
    root, _ = c.clip(0)
    assert root.shape == (45, 3) and np.isfinite(root).all()


def test_a_json_file_given_alone_gets_the_parsers_error(tmp_path):
    """Passed over in a folder, a JSON object without frames given alone is parsed, and the user
    reads why it is no DeepMimic clip."""
    f = tmp_path / "labels.json"
    f.write_text(json.dumps({"content": 6, "style": 11}))
    with pytest.raises(ValueError, match="no clip could be imported.*has no 'Frames' list"):
        import_motion(f, cache_dir=tmp_path / "cache", progress=False, workers=1)


PYBULLET = "pybullet==3.2.7"


@pytest.mark.slow
def test_pybullet_wheel_clips_do_what_their_names_say(tmp_path):
    """The real clips, from the wheel pip downloads: every humanoid clip imports, and the
    kinematic detectors of `eval impulses` fire on the clips they are named after."""
    from avatar_motor.body.motion_state import states_from_motion
    from avatar_motor.eval.control import impulse_success
    got = subprocess.run([sys.executable, "-m", "pip", "download", "--no-deps", "-q", PYBULLET, "-d", str(tmp_path)],
                         capture_output=True, text=True)
    wheels = list(tmp_path.glob("pybullet-*.whl"))
    if got.returncode or not wheels:
        pytest.skip(f"pip could not download {PYBULLET}: {got.stderr[-300:]}")
    path, summary = import_motion(wheels[0], progress=False, workers=1)
    c = MotionCache.load(path)
    assert len(c.clips) == 20 and [s["key"].split("/")[-1] for s in summary["skipped"]] == ["laikago_walk.txt"]

    def states(name):
        i = c.find(f"humanoid3d_{name}.txt")
        root, q = c.clip(i)
        R = rot.quat_to_matrix(torch.from_numpy(q).double())
        return states_from_motion(torch.from_numpy(root).double(), R[:, 0], R[:, 1:], rest_offsets(None, torch.float64))[None]

    # the kick is DeepMimic's right leg; the detectors look 1.5-2 s from the start
    kick = states("kick")
    assert impulse_success("right_kick", kick).all() and not impulse_success("left_kick", kick).any()
    assert impulse_success("back_flip", states("backflip")).all()
    assert impulse_success("forward_roll", states("roll")).all()
    for name in ("walk", "punch"):
        assert not impulse_success("back_flip", states(name)).any() and not impulse_success("forward_roll", states(name)).any()
    for i in range(len(c.clips)):  # on the ground, none below it by more than the ANCR margin
        root, q = c.clip(i)
        R = rot.quat_to_matrix(torch.from_numpy(q).double())
        J = forward_kinematics(torch.from_numpy(root).double(), R[:, 0], R[:, 1:], rest_offsets(None, torch.float64))[0]
        low = J[..., 1].min(-1).values
        assert low.min() > -0.05 and low.quantile(0.1) < 0.06, c.clips[i]["key"]
