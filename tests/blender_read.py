"""Run inside Blender (tests/test_blender.py): imports one BVH, glTF or FBX file into an empty
scene at 30 frames/s and prints, as one line "READ {json}", the joints it holds (armature bones or
glTF nodes), the number of frames of its animation, every joint's world position at the frames
asked for, in our axes (Blender's Z-up scene turned back to Y up), and, for a skinned mesh, the
bounding box of its vertices as Blender deforms them at those frames. With a third argument, a
.png path, it also renders the last of those frames there (Workbench, a camera at the body's side)."""
import builtins
import json
import sys

import bpy

args = sys.argv[sys.argv.index("--") + 1:]
path, frames, png = args[0], args[1], (args[2] if len(args) > 2 else None)
frames = [int(f) for f in frames.split(",")]
bpy.ops.wm.read_factory_settings(use_empty=True)
scene = bpy.context.scene
scene.render.fps, scene.render.fps_base = 30, 1.0  # without it Blender keys the clip at 24 frames/s
if path.endswith(".bvh"):
    import io_anim_bvh.import_bvh as import_bvh
    # Blender 3.4's importer opens the file in mode 'rU', which Python 3.11 refuses
    import_bvh.open = lambda p, mode="r", *a, **k: builtins.open(p, mode.replace("U", ""), *a, **k)
    bpy.ops.import_anim.bvh(filepath=path, global_scale=0.01, frame_start=1, use_fps_scale=False,
                            update_scene_fps=False, update_scene_duration=True)
elif path.endswith(".glb"):
    import numpy
    numpy.bool = bool  # Blender 3.4's glTF importer uses numpy.bool, gone from Debian's numpy 1.24
    bpy.ops.import_scene.gltf(filepath=path)
elif path.endswith(".fbx"):
    bpy.ops.import_scene.fbx(filepath=path)
else:
    raise SystemExit(f"unknown file type {path}")

armatures = [o for o in scene.objects if o.type == "ARMATURE"]
actions = list(bpy.data.actions)
first, last = (min(a.frame_range[0] for a in actions), max(a.frame_range[1] for a in actions)) if actions else (0, -1)
out = {"frames": int(round(last - first)) + 1, "first": first, "positions": {}}


def ours(v):
    return [v.x, v.z, -v.y]  # Blender (x, y, z), Z up -> ours (x, y, z), Y up


if armatures:
    arm = armatures[0]
    out["joints"] = [b.name for b in arm.data.bones]
    for f in frames:
        scene.frame_set(int(first) + f)
        out["positions"][f] = {b.name: ours(arm.matrix_world @ b.head) for b in arm.pose.bones}
else:  # our glTF: a node per joint, its mesh parts as children named after it
    joints = [o for o in scene.objects if o.type == "EMPTY"]
    out["joints"] = [o.name for o in joints]
    for f in frames:
        scene.frame_set(int(first) + f)
        out["positions"][f] = {o.name: ours(o.matrix_world.translation) for o in joints}
skinned = [o for o in scene.objects if o.type == "MESH" and any(m.type == "ARMATURE" for m in o.modifiers)]
if skinned:
    out["mesh_box"] = {}
    for f in frames:
        scene.frame_set(int(first) + f)
        deps = bpy.context.evaluated_depsgraph_get()
        ob = skinned[0].evaluated_get(deps)
        P = [ours(ob.matrix_world @ v.co) for v in ob.to_mesh().vertices]
        out["mesh_box"][f] = [[min(p[k] for p in P) for k in range(3)], [max(p[k] for p in P) for k in range(3)]]
        ob.to_mesh_clear()
if png:
    import mathutils
    scene.frame_set(int(first) + frames[-1])
    lo, hi = out["mesh_box"][frames[-1]] if skinned else ([0, 0, 0], [0, 1.8, 0])
    c = mathutils.Vector(((lo[0] + hi[0]) / 2, -(lo[2] + hi[2]) / 2, (lo[1] + hi[1]) / 2))  # back to Blender's axes
    cam = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    scene.collection.objects.link(cam)
    cam.location = c + mathutils.Vector((3.2, -3.2, 0.3))
    cam.rotation_euler = (c - cam.location).to_track_quat("-Z", "Y").to_euler()
    scene.camera = cam
    scene.render.engine = "BLENDER_WORKBENCH"
    scene.display.shading.light = "STUDIO"
    scene.render.resolution_x, scene.render.resolution_y = 480, 480
    scene.render.filepath = png
    bpy.ops.render.render(write_still=True)
print("READ " + json.dumps(out))
