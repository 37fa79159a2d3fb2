"""avatar-motor: a real-time generative motor system for interactive 3D avatars.

The Python API (avatar_motor/api.py): `am.load()` the shipped models, `am.Scene(model)` to spawn,
steer, push and run avatars, `scene.motion(avatar)` for named fields and `.save(path)`."""
__version__ = "0.1.0"

_API = ("Model", "Motion", "Scene", "load", "motion_of")


def __getattr__(name):  # the API on first use: `avatar-motor --help` needs no torch
    if name in _API:
        from . import api
        return getattr(api, name)
    raise AttributeError(f"module 'avatar_motor' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + list(_API))
