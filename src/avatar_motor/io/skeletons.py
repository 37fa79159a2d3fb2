"""Skeleton conventions of the tools exports go to (`--skeleton smpl|mixamo|ue5`): the joint names
each one's retargeters and importers look for. The body, its rest pose (our T-pose, on the
avatar's own bones) and its motion are the same in every convention: only names change, so an
exported file still reads back as exactly our FK. Units and axes are those of the file format:
BVH in centimetres with Y up (what BVH readers assume), glTF in metres with Y up (its
specification), FBX in centimetres with its axes in its header (written by Blender, fbx.py)."""
from __future__ import annotations

from ..body.skeleton import JOINT_NAMES

# canonical joint -> name, per convention; the Mixamo and Unreal names are the ones the importer
# also reads (data/retarget.py NAMINGS)
SKELETONS = ("smpl", "mixamo", "ue5")


def joint_names(skeleton: str = "smpl") -> list[str]:
    """Our 22 joints' names in a convention: smpl (ours), mixamo ('mixamorig:Hips', ...; Mixamo's
    spine is three joints, as ours), ue5 (the UE5 mannequin's pelvis, spine_01, spine_03,
    spine_05, neck_01, head, thigh_l, ...: its spine_02, spine_04 and neck_02 have no joint of
    ours, so a retargeter maps chains, as Unreal's IK Retargeter does)."""
    from ..data.retarget import NAMINGS
    if skeleton not in SKELETONS:
        raise ValueError(f"unknown skeleton {skeleton!r}; skeletons are {list(SKELETONS)}")
    if skeleton == "smpl":
        return list(JOINT_NAMES)
    names = NAMINGS[skeleton]
    if skeleton == "mixamo":
        return ["mixamorig:" + names[j] for j in JOINT_NAMES]
    return [names[j].lower() for j in JOINT_NAMES]  # Unreal's mannequin: thigh_l, calf_l, ...
