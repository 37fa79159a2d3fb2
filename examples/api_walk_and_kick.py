"""The Python API without a server: spawn two avatars, steer one, kick, push the other in physics
mode, and write what they did as BVH and glTF.

    python examples/api_walk_and_kick.py [OUT_DIR]
"""
import sys
from pathlib import Path

import avatar_motor as am

out = Path(sys.argv[1] if len(sys.argv) > 1 else "out")
out.mkdir(parents=True, exist_ok=True)
model = am.load()  # shipped weights: trained on CC BY-NC 4.0 data, non-commercial use only
print(f"model {model.name}; labels {model.labels}")
scene = am.Scene(model, seed=0)
walker = scene.spawn(position=(0.0, 0.0))
other = scene.spawn(position=(2.0, 0.0), yaw=3.14)

scene.goal(walker, velocity=(0.0, 1.2))  # walk along +z
scene.physics(other)  # the other body is simulated
scene.run(3.0)
scene.goal(walker, None)
scene.impulse(walker, "right_kick")
scene.force(other, "pelvis", (0.0, 0.0, 1500.0), 0.1)  # a 150 N s shove
scene.run(2.0)

for avatar, name in ((walker, "walker"), (other, "pushed")):
    m = scene.motion(avatar)
    pelvis = m.positions[:, 0]
    print(f"{name}: {len(m)} frames ({m.seconds:.1f} s), pelvis from ({pelvis[0, 0]:.2f}, {pelvis[0, 2]:.2f}) "
          f"to ({pelvis[-1, 0]:.2f}, {pelvis[-1, 2]:.2f}) m; rotations {tuple(m.rotations.shape)}")
    for ext in ("bvh", "glb"):
        print("wrote", m.save(out / f"{name}.{ext}"))
