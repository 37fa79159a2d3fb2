"""FBX export through Blender (Debian's `blender` package, or any `blender` on PATH): our BVH is
imported as an armature with its action and exported as FBX binary: the skeleton as bones (what
engines import as a skeleton), the motion baked at every frame, centimetres (FBX's unit scale),
the axes in the file's header (Blender's defaults, which Unity, Unreal and Godot read). Blender runs
in the background, in a process of its own, with a timeout."""
from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from pathlib import Path

from .bvh import BVH, write_bvh

BLENDER_TIMEOUT = 300  # s: a minute of motion converts in seconds; a hung Blender is stopped

# run inside Blender: argv after "--" are the BVH, the FBX to write and the frames per second
_SCRIPT = r'''
import builtins, sys
import bpy
import io_anim_bvh.import_bvh as import_bvh

src, dst, fps = sys.argv[sys.argv.index("--") + 1:]
# Blender 3.4's BVH importer opens files in mode 'rU', which Python 3.11 (Debian's Blender runs on
# it) refuses; the same file read in mode 'r'
import_bvh.open = lambda path, mode="r", *a, **k: builtins.open(path, mode.replace("U", ""), *a, **k)
bpy.ops.wm.read_factory_settings(use_empty=True)
scene = bpy.context.scene
scene.render.fps = round(float(fps))
scene.render.fps_base = round(float(fps)) / float(fps)
bpy.ops.import_anim.bvh(filepath=src, global_scale=0.01, frame_start=1, use_fps_scale=False,
                        update_scene_fps=False, update_scene_duration=True, rotate_mode="NATIVE",
                        axis_forward="-Z", axis_up="Y")
# the clip's frames and nothing after them (the empty scene's range is 1-250)
action = bpy.data.actions[0]
scene.frame_start, scene.frame_end = int(action.frame_range[0]), int(action.frame_range[1])
bpy.ops.export_scene.fbx(filepath=dst, object_types={"ARMATURE"}, add_leaf_bones=False, bake_anim=True,
                         bake_anim_use_all_actions=False, bake_anim_use_nla_strips=False,
                         bake_anim_simplify_factor=0.0, apply_unit_scale=True, use_armature_deform_only=False,
                         primary_bone_axis="Y", secondary_bone_axis="X")
print("FBX written")
'''


def blender() -> str:
    """The Blender executable, or a clear error saying how to get one."""
    exe = shutil.which("blender")
    if exe is None:
        raise ValueError("writing FBX needs Blender: install Debian's package (apt-get install blender) or put a "
                         "`blender` executable on PATH, then run again (BVH, glTF and npz need nothing)")
    return exe


def bvh_to_fbx(b: BVH, out: str | Path) -> Path:
    """Write the BVH's skeleton and motion as FBX binary at `out` (through Blender)."""
    exe = blender()
    with tempfile.TemporaryDirectory() as d:
        src, script = Path(d) / "motion.bvh", Path(d) / "to_fbx.py"
        write_bvh(src, b)
        script.write_text(_SCRIPT)
        env = {**os.environ, "HOME": d}  # Blender writes its user configuration there, not into the user's
        try:
            run = subprocess.run([exe, "-b", "--factory-startup", "-noaudio", "--python", str(script), "--",
                                  str(src), str(out), str(1.0 / b.frame_time)],
                                 capture_output=True, text=True, timeout=BLENDER_TIMEOUT, env=env)
        except subprocess.TimeoutExpired:
            raise ValueError(f"Blender did not finish writing {out} within {BLENDER_TIMEOUT} s") from None
        if run.returncode != 0 or "FBX written" not in run.stdout or not Path(out).exists():
            tail = (run.stdout + run.stderr)[-1500:]
            raise ValueError(f"Blender could not write {out} (exit {run.returncode}):\n{tail}")
    return Path(out)
