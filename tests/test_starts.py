"""Any frame is a good start: generate --init from a frame of a real-world capture gives an avatar
on the floor with the source character's proportions, and motion that stays realistic. With the
shipped model (a tiny random one only checks the mechanics)."""
import numpy as np
import pytest
import torch

from avatar_motor.body.motion_state import body_joints, body_mismatch, joints_of
from avatar_motor.body.skeleton import rest_offsets
from avatar_motor.cli import load_init, main
from avatar_motor.eval import metrics as M
from avatar_motor.eval.realism import BodyCheck, rollout
from avatar_motor.runtime.crowd import RuntimeConfig

from .conftest_models import SHIPPED, shipped_or_tiny
from .fixture_tools import MIX_PHASES, QUIRKS

SHIPPED_MODEL = (SHIPPED / "model.safetensors").exists()


@pytest.mark.parametrize("naming", list(QUIRKS))
def test_generate_from_a_real_world_file_keeps_its_body_and_reimports(quirky_files, tmp_path, naming):
    from avatar_motor.data.retarget import retarget
    from avatar_motor.io.bvh import read_bvh
    model = SHIPPED if SHIPPED_MODEL else shipped_or_tiny(tmp_path).path
    src = quirky_files / f"mix_{naming}.bvh"
    init, shape = load_init(f"{src}:{int(MIX_PHASES['crouching'] * 30)}")
    assert float(body_mismatch(init.double(), rest_offsets(shape, torch.float64)).max()) < 1e-5
    assert shape.abs().max() > 0.1  # the file's character, not the average body
    for ext in ("bvh", "npz"):
        out = tmp_path / f"g.{ext}"
        assert main(["generate", "--model", str(model), "--seconds", "2", "--init", f"{src}:30", "--out", str(out)]) == 0
    with np.load(tmp_path / "g.npz") as z:
        states, betas = torch.from_numpy(z["states"]).double(), torch.from_numpy(z["betas"])
    assert torch.allclose(betas, shape)
    assert float(body_mismatch(states, rest_offsets(shape, torch.float64)).max()) < 1e-3
    # the BVH carries that body: re-imported as it was written, it is the npz's motion
    b = read_bvh(tmp_path / "g.bvh")
    from avatar_motor.body.skeleton import JOINT_NAMES
    order = [b.names.index(n) for n in JOINT_NAMES]
    assert np.allclose(b.offsets[order][1:], rest_offsets(shape, torch.float64).numpy()[1:] * 100, atol=1e-4)  # its bones, in cm
    # our files' axes are known (X left, Y up, Z forward); judged from the body (detect_axes snaps
    # the median hip direction to an axis) a clip that turns past 45 degrees comes back turned
    r = retarget(b, ground="keep", body="source", axes=np.eye(3))
    assert r.info["skeleton"] == "smpl" and r.root_pos.shape == (60, 3)
    assert np.allclose(r.root_pos, states[:, :3].numpy(), atol=1e-4)
    assert float(body_joints(states, rest_offsets(shape, torch.float64))[..., 1].min()) > -0.02


@pytest.mark.skipif(not SHIPPED_MODEL, reason="needs the shipped model")
def test_ten_starting_frames_stay_on_the_floor_and_do_not_skate(quirky_files, artifacts):
    """Standing, crouching and mid-stride frames of the three real-world fixtures and a walking
    frame of the LAFAN1 one, on each file's own body shape: 8 s each."""
    from avatar_motor.model.checkpoint import load_checkpoint
    from avatar_motor.viz import contact_sheet
    from .fixture_tools import FIXTURES
    specs = [f"{quirky_files / f'mix_{n}.bvh'}:{int(MIX_PHASES[p] * 30)}" for n in QUIRKS for p in ("standing", "crouching", "mid-stride")]
    specs.append(f"{FIXTURES / 'walk_lafan1.bvh'}:17")
    inits = [load_init(s) for s in specs]
    check = BodyCheck()
    X = rollout(load_checkpoint(SHIPPED), torch.stack([i for i, _ in inits]), torch.stack([s for _, s in inits]), 240,
                RuntimeConfig(), 0, check=check)
    J = joints_of(X)
    lowest = J[..., 1].amin(-1)
    assert check.summary()["body_mismatch_max_mm"] < 1.0
    assert float(lowest.min()) > -0.02  # no frame sinks into the floor
    assert M.asr(J) <= 0.05
    assert not M.frozen(J).any()
    contact_sheet([J[k, ::10].numpy() for k in range(len(specs))], artifacts / "starts.png",
                  titles=[s.rsplit("/", 1)[-1] for s in specs])


def test_exported_files_show_the_body_the_runtime_emitted(tmp_path):
    """BVH and glTF read back from the files alone (their own hierarchy, offsets, rotations) put
    every joint where the runtime's state says, on the avatar's own bones; the realism report
    reads them the same way."""
    from avatar_motor.eval.realism import exported_files
    from avatar_motor.io.bvh import read_bvh
    from avatar_motor.io.export import BVH_SCALE, write_motion
    from avatar_motor.io.gltf import read_glb_joints
    from avatar_motor.body.skeleton import JOINT_NAMES
    from avatar_motor.runtime.crowd import Crowd
    crowd = Crowd(shipped_or_tiny(tmp_path), seed=3)
    shape = torch.tensor([1.5, -1.0, 0.5, 1.0, -0.5, 0.8])
    i = crowd.spawn(shape=shape)
    crowd.push(i, "head", (1.0, 0.0, 2.0))
    X = torch.cat([crowd.step_segment()[i] for _ in range(3)])
    J = body_joints(X.double(), rest_offsets(shape, torch.float64))
    assert torch.allclose(J, joints_of(X).double(), atol=1e-5)
    bvh, glb = write_motion(tmp_path / "m.bvh", X, shape), write_motion(tmp_path / "m.glb", X, shape)
    b = read_bvh(bvh)
    P = torch.from_numpy(b.global_transforms()[0] / BVH_SCALE)[:, [b.names.index(n) for n in JOINT_NAMES]]
    names, G = read_glb_joints(glb)
    G = torch.from_numpy(G)[:, [names.index(n) for n in JOINT_NAMES]]
    assert (P - J).norm(dim=-1).max() < 1e-5 and (G - J).norm(dim=-1).max() < 1e-5
    r = exported_files([bvh, glb])
    assert r["exported_files"] == 2 and r["exported_lowest_joint_m"] == pytest.approx(float(J[..., 1].min()), abs=1e-5)
