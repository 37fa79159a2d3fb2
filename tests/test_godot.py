"""The Godot add-on (engines/godot) against a live server, in Debian's headless Godot 3
(`godot3-server`, which `make test` installs): it connects, spawns an avatar, poses a Skeleton from
the binary stream with Godot's own FK landing on the streamed positions, and its commands are
acknowledged (engines/godot/tests/smoke.gd)."""
import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from avatar_motor.runtime.crowd import RuntimeConfig
from avatar_motor.serve.world import World

from .conftest_models import tiny_motor
from .test_server import Running

GODOT = shutil.which("godot3-server")
PROJECT = Path(__file__).resolve().parents[1] / "engines" / "godot"


@pytest.mark.skipif(GODOT is None, reason="Debian's godot3-server not installed (make test installs it)")
def test_the_godot_add_on_drives_a_skeleton_from_a_live_server(tmp_path):
    world = World(tiny_motor(tmp_path), RuntimeConfig(backend="torch"), seed=0)
    world.apply({"type": "spawn"}, log=False)
    srv = Running(world, max_avatars=4, per_client=4)  # not the cap measured at start-up: the machine may be busy
    try:
        # Godot writes its user data and the project's import cache: both into tmp_path, so the
        # checkout stays clean
        project = tmp_path / "godot"
        shutil.copytree(PROJECT, project)
        env = {**os.environ, "AVATAR_MOTOR_URL": srv.url, "HOME": str(tmp_path), "XDG_DATA_HOME": str(tmp_path / "data")}
        run = subprocess.run([GODOT, "--path", str(project), "-s", "res://tests/smoke.gd"], env=env,
                             capture_output=True, text=True, timeout=180)
    finally:
        srv.stop()
    lines = [ln for ln in run.stdout.splitlines() if ln.startswith("RESULT ")]
    assert lines, f"no result from Godot (exit {run.returncode}):\n{run.stdout[-2000:]}\n{run.stderr[-2000:]}"
    result = json.loads(lines[-1][len("RESULT "):])
    print("godot:", result)
    assert result["problem"] == "", result
    assert result["bones"] == 22 and result["frames_posed"] >= 60, result
    assert result["fk_max_error_m"] < 1e-3, result  # Godot's FK of our rotations is our body
    assert result["wrist_moved_m"] > 0.05, result  # the bone moves
    assert result["acks"] == [True, True], result  # the goal and the impulse were acknowledged
    assert run.returncode == 0, run.stdout[-2000:]
    commands = [e["cmd"]["type"] for e in world.events]
    assert "goal" in commands and "impulse" in commands
    # and the demo scene a user opens loads, its scripts parsed
    demo = subprocess.run([GODOT, "--path", str(project), "-s", "res://tests/load_demo.gd"], env=env,
                          capture_output=True, text=True, timeout=120)
    assert "DEMO ok" in demo.stdout and demo.returncode == 0, demo.stdout[-2000:] + demo.stderr[-2000:]
