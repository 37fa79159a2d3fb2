"""Connect to a running `avatar-motor serve`, walk avatar 0 in a square, kick, print frames."""
import sys

from avatar_motor.client import Client

url = sys.argv[1] if len(sys.argv) > 1 else "ws://127.0.0.1:8765/ws"
with Client(url) as c:
    print("model", c.welcome["model"], "joints", len(c.welcome["joint_names"]))
    for vx, vz in [(1.2, 0), (0, 1.2), (-1.2, 0), (0, -1.2)]:
        print(c.command({"type": "goal", "avatar": 0, "velocity": [vx, vz]}))
        for f in c.frames(60):
            p = f["avatars"][0]["positions"][0]
        print(f"frame {f['frame']}: pelvis at x={p[0]:.2f} z={p[2]:.2f}")
    print(c.command({"type": "impulse", "avatar": 0, "preset": "left_kick"}))
    print(c.command({"type": "goal", "avatar": 0, "velocity": None}))
