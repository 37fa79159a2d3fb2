"""The Python API (avatar_motor/api.py): `import avatar_motor as am`."""
import pytest
import torch

import avatar_motor as am
from avatar_motor.body.skeleton import forward_kinematics, rest_offsets
from avatar_motor.body import rotations as rot
from avatar_motor.paths import DEFAULT_MODEL

from .conftest_models import tiny_motor


def test_a_scene_runs_avatars_and_gives_named_fields_that_are_one_body(tmp_path):
    scene = am.Scene(am.Model(tiny_motor(tmp_path)), seed=0)
    a = scene.spawn(position=(1.0, 2.0))
    b = scene.spawn(position=(-1.0, 0.0), yaw=1.0, shape=[0.5, 0, 0, 0, 0, 0])
    assert scene.avatars == [a, b]
    scene.goal(a, velocity=(0.0, 1.0))
    joints = scene.step()
    assert set(joints) == {a, b} and joints[a].shape == (22, 3)
    scene.run(1.0)
    m = scene.motion(a)
    assert len(m) == 1 + 1 + 30 and m.positions.shape == (32, 22, 3) and m.rotations.shape == (32, 22, 4)
    assert m.joint_names[0] == "pelvis" and abs(m.seconds - 32 / 30) < 1e-9
    assert torch.allclose(m.positions[0, 0, [0, 2]], torch.tensor([1.0, 2.0]))  # spawned where asked
    # positions are FK of the rotations on the avatar's own bones: one body, as exporters write it
    R = rot.quat_to_matrix(m.rotations.double())
    J, _ = forward_kinematics(m.positions[:, 0].double(), R[:, 0], R[:, 1:], rest_offsets(m.shape, torch.float64))
    assert float((J - m.positions.double()).abs().max()) < 1e-4
    assert len(scene.motion(b, seconds=0.5)) == 15 and torch.equal(scene.motion(b).shape, torch.tensor([0.5, 0, 0, 0, 0, 0]))
    for ext in ("bvh", "glb", "npz"):
        assert m.save(tmp_path / f"a.{ext}").stat().st_size > 1000
    with pytest.raises(ValueError, match="no avatar 7"):
        scene.motion(7)
    with pytest.raises(ValueError, match="unknown impulse preset"):
        scene.impulse(a, "moonwalk")
    scene.remove(b)
    assert scene.avatars == [a]


def test_a_scene_keeps_only_what_it_is_told_to(tmp_path):
    scene = am.Scene(am.Model(tiny_motor(tmp_path)), keep_seconds=0.5)
    a = scene.spawn()
    scene.run(1.0)
    assert len(scene.motion(a)) == 15


@pytest.mark.skipif(not (DEFAULT_MODEL / "config.json").exists(), reason="the shipped model is not in models/")
def test_load_gives_the_shipped_family():
    model = am.load()
    assert model.name == DEFAULT_MODEL.name and "bow" in model.labels and model.range_of_motion is not None
    assert not am.load(adaptors=False).adaptors


@pytest.mark.slow
def test_the_wheel_serves_the_studio_and_runs_the_api_in_a_fresh_environment(tmp_path):
    """`make wheel`, then in a new virtual environment: `pip install` the wheel, `avatar-motor
    serve` serves the studio with the shipped models, and the API example writes a BVH."""
    import shutil
    import socket
    import subprocess
    import sys
    import time
    import urllib.request
    from pathlib import Path
    root = Path(__file__).resolve().parents[1]
    subprocess.run(["make", "wheel"], cwd=root, check=True, capture_output=True)
    (wheel,) = (root / "dist").glob("avatar_motor-*.whl")
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    subprocess.run([str(venv / "bin" / "pip"), "install", "-q", str(wheel)], check=True, capture_output=True)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    server = subprocess.Popen([str(venv / "bin" / "avatar-motor"), "serve", "--port", str(port), "--max-avatars", "4"],
                              cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        page = ""
        for _ in range(120):
            try:
                page = urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=2).read().decode()
                break
            except OSError:
                time.sleep(0.5)
        assert "avatar-motor studio" in page
        info = urllib.request.urlopen(f"http://127.0.0.1:{port}/api/info", timeout=5).read().decode()
        assert "primal-bandai-emdm" in info
        human = urllib.request.urlopen(f"http://127.0.0.1:{port}/api/human?avatar=0&detail=low", timeout=30).read()
        assert human.startswith(b"glTF")  # the skinned human's asset, with its low detail, in the wheel
    finally:
        server.terminate()
        server.wait(10)
    example = shutil.copy(root / "examples" / "api_walk_and_kick.py", tmp_path)
    subprocess.run([str(venv / "bin" / "python"), example, str(tmp_path / "out")], cwd=tmp_path, check=True,
                   capture_output=True)
    assert (tmp_path / "out" / "walker.bvh").read_text().startswith("HIERARCHY")
