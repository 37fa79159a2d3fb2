"""The Python API, `import avatar_motor as am`: drive avatars without a server.

    import avatar_motor as am

    model = am.load()                        # the shipped models (non-commercial: Bandai data)
    scene = am.Scene(model, seed=0)
    a = scene.spawn(position=(0.0, 0.0))     # x, z on the ground; y is up, the avatar faces +z
    scene.goal(a, velocity=(0.0, 1.2))       # walk along +z at 1.2 m/s
    scene.run(3.0)
    scene.impulse(a, "left_kick")            # also: push, label, target, physics, force, throw
    scene.run(2.0)
    motion = scene.motion(a)                 # everything avatar a showed, as named fields
    motion.positions                         # (T, 22, 3) joint positions, metres, world
    motion.save("walk.bvh")                  # or .glb / .npz

A Scene is the runtime's Crowd (runtime/crowd.py) stepped on a virtual clock: `run` generates
what the avatars need and advances every avatar frame by frame, as the server does at 30 frames
per second, only as fast as this machine goes.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import torch

from .body import rotations as rot
from .body.motion_state import FPS, STATE_DIM, unpack
from .body.skeleton import JOINT_NAMES


@dataclass
class Model:
    """A loaded motion model with what runs beside it: its adaptors (action labels, styles,
    reaching) and physics mode's joint limits."""
    motor: object  # model.checkpoint.Motor
    adaptors: list = field(default_factory=list)
    range_of_motion: object = None

    @property
    def name(self) -> str:
        return self.motor.name

    @property
    def labels(self) -> list[str]:
        """The action and style labels its adaptors know."""
        return [lab for ad in self.adaptors if ad.cfg.control == "label" for lab in ad.cfg.labels]


def load(model: str | Path | None = None, adaptors: bool = True) -> Model:
    """The shipped default model (the one-step EMDM generator on the shipped base), or the
    checkpoint folder `model`; with the shipped adaptors trained on its base and the shipped
    joint limits. The shipped weights are trained on CC BY-NC 4.0 data: non-commercial use only."""
    from .model.adaptor import default_adaptors
    from .model.checkpoint import load_checkpoint
    from .paths import DEFAULT_MODEL, MODELS
    from .physics.limits import default_range

    motor = load_checkpoint(model or DEFAULT_MODEL)
    return Model(motor, default_adaptors(motor, MODELS) if adaptors else [], default_range(MODELS))


@dataclass
class Motion:
    """Frames of one avatar, as exporters write them (one body: positions are FK of rotations)."""
    positions: torch.Tensor  # (T, 22, 3) joint positions, metres, world frame, y up
    rotations: torch.Tensor  # (T, 22, 4) quaternions (w, x, y, z): joint 0 in the world, each other relative to its parent
    shape: torch.Tensor  # (6,) the body's shape parameters
    states: torch.Tensor  # (T, 267) the runtime's states (body/motion_state.py), what `save` writes
    fps: float = FPS
    joint_names: tuple[str, ...] = tuple(JOINT_NAMES)

    def __len__(self) -> int:
        return len(self.states)

    @property
    def seconds(self) -> float:
        return len(self) / self.fps

    def save(self, path: str | Path, skeleton: str = "smpl") -> Path:
        """Write BVH (.bvh), glTF (.glb), the states (.npz) or FBX (.fbx, through Blender), by the
        file's extension; skeleton: the joints' names, smpl (ours), mixamo or ue5."""
        from .io.export import write_motion
        return write_motion(path, self.states, self.shape, self.fps, skeleton=skeleton)


def motion_of(states: torch.Tensor, shape: torch.Tensor | None = None) -> Motion:
    """A Motion from runtime states (T, 267)."""
    states = states.float()
    u = unpack(states)
    R = u.rotations  # (T, 22, 3, 3)
    return Motion(u.joints.clone(), rot.matrix_to_quat(R), torch.zeros(6) if shape is None else shape.float(), states)


class Scene:
    """Avatars of one model on a shared virtual clock (see the module's docstring)."""

    def __init__(self, model: Model | None = None, seed: int = 0, config=None, keep_seconds: float | None = None):
        """config: a runtime.crowd.RuntimeConfig (default: the runtime's); keep_seconds: how much of
        each avatar's motion `motion` can return (None: all of it)."""
        from .runtime.crowd import Crowd, RuntimeConfig

        self.model = model or load()
        self.crowd = Crowd(self.model.motor, config or RuntimeConfig(), seed, self.model.adaptors,
                           self.model.range_of_motion)
        self.keep = None if keep_seconds is None else max(1, round(keep_seconds * FPS))
        self.frame = 0
        self._shown: dict[int, list[torch.Tensor]] = {}

    # ---------------------------------------------------------------- avatars
    def spawn(self, position=(0.0, 0.0), yaw: float = 0.0, shape=None, state=None) -> int:
        """A standing avatar at ground position (x, z) facing yaw (radians, 0 = +z), or starting from
        a runtime state (267,); shape: 6 body-shape parameters (0: the average body). Returns its id."""
        i = self.crowd.spawn(None if state is None else torch.as_tensor(state),
                             None if shape is None else torch.as_tensor(shape, dtype=torch.float32), position, yaw)
        self._shown[i] = [self.crowd.state(i)]
        return i

    def remove(self, avatar: int) -> None:
        self.crowd.remove(avatar)
        self._shown.pop(avatar, None)

    @property
    def avatars(self) -> list[int]:
        return self.crowd.ids()

    # ---------------------------------------------------------------- control (from the next frame)
    def goal(self, avatar: int, velocity=None, facing=None) -> None:
        """Walk or run at velocity (vx, vz) m/s on the ground, optionally facing (fx, fz); None stops steering."""
        self.crowd.set_goal(avatar, velocity, facing)

    def push(self, avatar: int, joint: str | int, velocity, frame: str = "world") -> None:
        """Add a velocity (vx, vy, vz) m/s to one joint ("world" or the avatar's "body" frame)."""
        self.crowd.push(avatar, joint, velocity, frame)

    def impulse(self, avatar: int, preset: str, scale: float = 1.0) -> None:
        """One of the impulse presets: left_kick, right_kick, forward_run, back_flip, forward_roll."""
        self.crowd.impulse(avatar, preset, scale)

    def label(self, avatar: int, label: str | None, scale: float | None = None) -> None:
        """An action or style label of the shipped adaptors (Model.labels); None releases it.
        scale: the adaptor's strength (None: the one its card measures)."""
        self.crowd.set_label(avatar, label, scale)

    def persona(self, avatar: int, description: str | None) -> None:
        """Who the avatar is, in words ("a weary old man"), or a characterized name (`adapt
        persona`), with a persona model (am.load("models/primal-bandai-persona")); None releases it."""
        self.crowd.set_persona(avatar, description)

    def target(self, avatar: int, position, scale: float | None = None) -> None:
        """Walk to the ground point (x, z) with the reaching adaptor; None releases it. scale: as for label."""
        self.crowd.set_target(avatar, position, scale)

    def physics(self, avatar: int, on: bool = True) -> None:
        """Physics mode (DROP): the body is simulated, the model is its control."""
        self.crowd.set_physics(avatar, on)

    def force(self, avatar: int, joint: str | int, force, seconds: float) -> None:
        """Hold a world force (N) on a joint for `seconds` (physics mode)."""
        self.crowd.apply_force(avatar, joint, force, seconds)

    def throw(self, avatar: int, position, velocity, mass: float = 1.0) -> None:
        """Throw a ball (world position, velocity m/s, mass kg) that the avatar's simulation sees."""
        self.crowd.throw(avatar, position, velocity, mass)

    # ---------------------------------------------------------------- time
    def step(self) -> dict[int, torch.Tensor]:
        """One frame (1/30 s) for every avatar: returns each one's joint positions (22, 3)."""
        shown = self.crowd.next_frames()
        self.frame += 1
        for i, x in shown.items():
            frames = self._shown.setdefault(i, [])
            frames.append(x)
            if self.keep is not None and len(frames) > self.keep:
                del frames[: len(frames) - self.keep]
        return {i: unpack(x[None]).joints[0] for i, x in shown.items()}

    def run(self, seconds: float) -> None:
        """Advance the clock by `seconds`."""
        if not seconds >= 0:
            raise ValueError(f"seconds must be >= 0, got {seconds}")
        for _ in range(round(seconds * FPS)):
            self.step()

    def motion(self, avatar: int, seconds: float | None = None) -> Motion:
        """What avatar `avatar` showed since it was spawned (or in the last `seconds`)."""
        if avatar not in self._shown:
            raise ValueError(f"no avatar {avatar}; avatars are {self.avatars}")
        frames = self._shown[avatar]
        if seconds is not None:
            frames = frames[-max(1, round(seconds * FPS)):]
        return motion_of(torch.stack(frames), self.crowd.shape(avatar))


__all__ = ["Model", "Motion", "Scene", "load", "motion_of", "STATE_DIM"]
