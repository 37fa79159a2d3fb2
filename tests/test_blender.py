"""Exports read by a third party: Debian's headless Blender (which `make test` installs) imports our
BVH, glTF and FBX files, in each joint-naming convention, and must find the joints under their
names, every frame, and each joint where our FK puts it (tests/blender_read.py)."""
import json
import shutil
import subprocess
from pathlib import Path

import pytest
import torch

from avatar_motor.body.motion_state import joints_of
from avatar_motor.io.export import write_motion
from avatar_motor.io.skeletons import joint_names
from avatar_motor.runtime.crowd import Crowd, RuntimeConfig

from .conftest_models import shipped_or_tiny

BLENDER = shutil.which("blender")
READER = Path(__file__).with_name("blender_read.py")
FRAMES = (0, 17, 44)
needs_blender = pytest.mark.skipif(BLENDER is None, reason="Debian's blender not installed (make test installs it)")


def _walk(tmp_path, frames=45):
    """A walk of a body of its own shape: world states (frames, 267) and the shape."""
    crowd = Crowd(shipped_or_tiny(tmp_path), RuntimeConfig(backend="torch"), seed=3)
    shape = torch.tensor([1.0, -0.5, 0.5, 0.0, 0.5, -0.5])
    i = crowd.spawn(shape=shape)
    crowd.set_goal(i, (0.3, 1.2))
    X = torch.cat([crowd.step_segment()[i] for _ in range(frames // 15)])
    return X, shape


def _read(path: Path, png: Path | None = None) -> dict:
    run = subprocess.run([BLENDER, "-b", "--factory-startup", "-noaudio", "--python", str(READER), "--", str(path),
                          ",".join(map(str, FRAMES)), *([str(png)] if png else [])], capture_output=True, text=True,
                         timeout=300)
    lines = [ln for ln in run.stdout.splitlines() if ln.startswith("READ ")]
    assert lines, f"Blender read nothing from {path.name} (exit {run.returncode}):\n{(run.stdout + run.stderr)[-2000:]}"
    return json.loads(lines[-1][len("READ "):])


@needs_blender
@pytest.mark.parametrize("suffix,skeleton", [(".bvh", "smpl"), (".bvh", "ue5"), (".glb", "mixamo"), (".fbx", "ue5"),
                                             (".fbx", "mixamo")])
def test_blender_reads_our_exports_as_our_body(tmp_path, suffix, skeleton):
    X, shape = _walk(tmp_path)
    path = write_motion(tmp_path / f"walk{suffix}", X, shape, skeleton=skeleton)
    got = _read(path)
    names = joint_names(skeleton)
    assert set(names) <= set(got["joints"]), (names, got["joints"])
    assert got["frames"] == len(X)
    J = joints_of(X.double())  # our FK: what the studio drew and the metrics read
    worst = max(abs(got["positions"][str(f)][n][k] - float(J[f, j, k]))
                for f in FRAMES for j, n in enumerate(names) for k in range(3))
    assert worst < 1e-3, f"{path.name}: a joint {worst * 1000:.2f} mm from our FK"


@needs_blender
def test_blender_skins_our_human_around_our_joints(tmp_path, artifacts):
    # the skinned human of a glTF export, deformed by Blender's own skinning mid-walk: its
    # vertices surround the joints of our FK (the head's top above the head joint, the soles at
    # the ground), so Blender poses the mesh as the studio does; rendered for a look
    X, shape = _walk(tmp_path)
    path = write_motion(tmp_path / "walk.glb", X, shape)
    got = _read(path, artifacts / "blender-walk.png")
    J = joints_of(X.double())
    for f in FRAMES:
        lo, hi = (torch.tensor(v, dtype=torch.float64) for v in got["mesh_box"][str(f)])
        jlo, jhi = J[f].min(0).values, J[f].max(0).values
        assert (lo <= jlo + 0.01).all() and (hi >= jhi - 0.01).all(), (f, lo, hi, jlo, jhi)  # the joints inside
        assert (jlo - lo).max() < 0.3 and (hi - jhi).max() < 0.3, (f, lo, hi, jlo, jhi)  # and the mesh close about them
        assert abs(float(lo[1])) < 0.05  # on the ground
    assert (artifacts / "blender-walk.png").stat().st_size > 10_000


def test_fbx_without_blender_names_the_package_and_writes_nothing(tmp_path, monkeypatch):
    X = torch.zeros(2, 267)
    monkeypatch.setattr(shutil, "which", lambda exe: None)
    with pytest.raises(ValueError, match="apt-get install blender"):
        write_motion(tmp_path / "walk.fbx", X)
    assert not list(tmp_path.iterdir())
    with pytest.raises(ValueError, match="unknown skeleton"):
        write_motion(tmp_path / "walk.bvh", X, skeleton="maya")
