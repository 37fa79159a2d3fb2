"""The streaming protocol, version 1 (documented in docs/protocol.md): command validation and
frame encoding. Commands are JSON text messages; frames are binary (default) or JSON."""
from __future__ import annotations

import json
import math
import re
import struct

import numpy as np

from ..body.skeleton import JOINT_NAMES, SHAPE_DIM

VERSION = 1
MAX_MESSAGE_BYTES = 16 * 1024  # a longer command gets an error reply
MAX_SOCKET_MESSAGE_BYTES = 1024 * 1024  # a longer WebSocket message closes the connection (code 1009)
FRAME_MAGIC = b"AMF1"
FRAME_HEADER = struct.Struct("<4sIHH")  # magic, frame index, avatar count, joint count
AVATAR_RECORD = 4 + 22 * 3 * 4 + 22 * 4 * 4  # uint32 id, float32 positions, float32 quaternions


class ProtocolError(ValueError):
    """A malformed message: the reply names the field and what is expected, and carries the
    message's id when it had a valid one (so a client waiting for that reply gets it)."""

    def __init__(self, message: str, id: int | str | None = None):
        super().__init__(message)
        self.id = id


def _num(v, what: str, lo: float = -1e4, hi: float = 1e4) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not lo <= v <= hi:
        raise ProtocolError(f"{what} must be a finite number in [{lo:g}, {hi:g}], got {v!r}")
    return float(v)


def _vec(v, n: int, what: str, lo: float = -1e4, hi: float = 1e4) -> list[float]:
    if not isinstance(v, list) or len(v) != n:
        raise ProtocolError(f"{what} must be a list of {n} numbers, got {v!r}"[:200])
    return [_num(x, what, lo, hi) for x in v]


def _int(v, what: str, lo: int = 0, hi: int = 2**31 - 1) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
        raise ProtocolError(f"{what} must be an integer in [{lo}, {hi}], got {v!r}"[:200])
    return v


# per command: required and optional fields with their validators
_FIELDS = {
    "hello": ({}, {"version": lambda v: _int(v, "version"), "format": lambda v: _choice(v, ("binary", "json"), "format"),
                   "token": lambda v: _str(v, "token")}),
    "spawn": ({}, {"position": lambda v: _vec(v, 2, "position"), "yaw": lambda v: _num(v, "yaw", -100, 100),
                   "shape": lambda v: _vec(v, SHAPE_DIM, "shape", -3, 3)}),
    "remove": ({"avatar": lambda v: _int(v, "avatar")}, {}),
    "impulse": ({"avatar": lambda v: _int(v, "avatar"), "preset": lambda v: _str(v, "preset")},
                {"scale": lambda v: _num(v, "scale", 0, 5)}),
    "push": ({"avatar": lambda v: _int(v, "avatar"), "joint": lambda v: _joint(v),
              "velocity": lambda v: _vec(v, 3, "velocity (m/s)", -30, 30)},
             {"frame": lambda v: _choice(v, ("world", "body"), "frame")}),
    "goal": ({"avatar": lambda v: _int(v, "avatar")},
             {"velocity": lambda v: None if v is None else _vec(v, 2, "velocity (vx, vz m/s)", -8, 8),
              "facing": lambda v: None if v is None else _vec(v, 2, "facing (fx, fz)")}),
    "target": ({"avatar": lambda v: _int(v, "avatar")},
               {"position": lambda v: None if v is None else _vec(v, 2, "position (x, z m)", -1000, 1000),
                "speed": lambda v: _num(v, "speed", 0.1, 6), "scale": lambda v: _num(v, "scale", 0, 10)}),
    "label": ({"avatar": lambda v: _int(v, "avatar"), "label": lambda v: None if v is None else _str(v, "label")},
              {"scale": lambda v: _num(v, "scale", 0, 10)}),
    "persona": ({"avatar": lambda v: _int(v, "avatar"),
                 "description": lambda v: None if v is None else _str(v, "description", 300)}, {}),
    "reset": ({}, {"avatar": lambda v: _int(v, "avatar")}),
    # physics mode (DROP): the body is simulated, the model its control
    "physics": ({"avatar": lambda v: _int(v, "avatar"), "on": lambda v: _bool(v, "on")}, {}),
    "force": ({"avatar": lambda v: _int(v, "avatar"), "joint": lambda v: _joint(v),
               "force": lambda v: _vec(v, 3, "force (N)", -5000, 5000), "seconds": lambda v: _num(v, "seconds", 0.01, 10)}, {}),
    "spring": ({"avatar": lambda v: _int(v, "avatar"), "joint": lambda v: _joint(v),
                "target": lambda v: None if v is None else _vec(v, 3, "target (x, y, z m)", -1000, 1000)},
               {"stiffness": lambda v: _num(v, "stiffness (N/m)", 1, 5000)}),
    "ball": ({"avatar": lambda v: _int(v, "avatar"), "position": lambda v: _vec(v, 3, "position (x, y, z m)", -1000, 1000),
              "velocity": lambda v: _vec(v, 3, "velocity (m/s)", -60, 60)},
             {"mass": lambda v: _num(v, "mass (kg)", 0.01, 100), "radius": lambda v: _num(v, "radius (m)", 0.02, 1)}),
    # the world of physics mode (DROP 8.2): a tilted ground, static boxes on the floor
    "ground": ({"tilt": lambda v: _vec(v, 2, "tilt (degrees about x, about z)", -30, 30)},
               {"pivot": lambda v: _vec(v, 2, "pivot (x, z m)", -1000, 1000),
                "seconds": lambda v: _num(v, "seconds", 0, 60)}),
    "obstacle": ({"centre": lambda v: _vec(v, 2, "centre (x, z m)", -1000, 1000),
                  "size": lambda v: _vec(v, 3, "size (x, y, z m)", 0.02, 3)},
                 {"yaw": lambda v: _num(v, "yaw (degrees)", -360, 360)}),
    "remove_obstacle": ({}, {"obstacle": lambda v: _int(v, "obstacle")}),
    "seed": ({"seed": lambda v: _int(v, "seed")}, {}),
}
COMMANDS = sorted(_FIELDS)


def _str(v, what: str, longest: int = 200) -> str:
    if not isinstance(v, str) or not 0 < len(v.strip()) or len(v) > longest:
        raise ProtocolError(f"{what} must be a non-empty string of at most {longest} characters")
    return v


def _bool(v, what: str) -> bool:
    if not isinstance(v, bool):
        raise ProtocolError(f"{what} must be true or false, got {v!r}"[:200])
    return v


def _choice(v, options, what: str):
    if v not in options:
        raise ProtocolError(f"{what} must be one of {list(options)}, got {v!r}"[:200])
    return v


def _joint(v):
    if isinstance(v, str):
        if v not in JOINT_NAMES:
            raise ProtocolError(f"joint must be a joint name {JOINT_NAMES} or index 0..21, got {v!r}"[:300])
        return v
    return _int(v, "joint", 0, 21)


_ID = re.compile(r'"id"\s*:\s*(?:(-?\d{1,18})\b|"([^"\\]{0,64})")')


def parse_message(text: str | bytes) -> dict:
    """Text of one client message -> validated command dict (keeps an optional 'id')."""
    if isinstance(text, bytes):
        raise ProtocolError("commands are JSON text messages, not binary")
    if len(text) > MAX_MESSAGE_BYTES:  # not parsed; its id, if near an end, is found for the reply
        m = _ID.search(text[:256]) or _ID.search(text[-256:])
        raise ProtocolError(f"message of {len(text)} bytes exceeds {MAX_MESSAGE_BYTES}",
                            id=(int(m[1]) if m[1] else m[2]) if m else None)
    try:
        msg = json.loads(text)
    except (json.JSONDecodeError, RecursionError) as e:
        raise ProtocolError(f"not valid JSON: {str(e)[:100]}") from None
    return validate_command(msg)


def _message_id(msg: dict):
    """The message's id if it is a valid one (an integer or a string of at most 64 characters)."""
    cid = msg.get("id")
    if isinstance(cid, bool) or not isinstance(cid, (int, str)) or len(str(cid)) > 64:
        return None
    return cid


def validate_command(msg) -> dict:
    if not isinstance(msg, dict):
        raise ProtocolError("a command must be a JSON object with a 'type'")
    cid = _message_id(msg)
    try:
        return _validate(msg, cid)
    except ProtocolError as e:
        e.id = cid
        raise


def _validate(msg: dict, cid) -> dict:
    kind = msg.get("type")
    if not isinstance(kind, str) or kind not in _FIELDS:
        raise ProtocolError(f"unknown command type {kind!r}; commands are {COMMANDS}"[:300])
    required, optional = _FIELDS[kind]
    out = {"type": kind}
    if "id" in msg:
        if cid is None:
            raise ProtocolError("id must be an integer or a string of at most 64 characters")
        out["id"] = cid
    for k, check in required.items():
        if k not in msg:
            raise ProtocolError(f"{kind}: missing field {k!r}")
        out[k] = check(msg[k])
    for k, check in optional.items():
        if k in msg:
            out[k] = check(msg[k])
    unknown = set(msg) - set(required) - set(optional) - {"type", "id"}
    if unknown:
        raise ProtocolError(f"{kind}: unknown fields {sorted(unknown)[:5]}")
    return out


def encode_frame_binary(frame: int, ids: list[int], joints: np.ndarray, quats: np.ndarray) -> bytes:
    """Little-endian: header (magic 'AMF1', uint32 frame, uint16 avatars, uint16 joints=22) then
    per avatar uint32 id, 66 float32 positions, 88 float32 quaternions (x, y, z, w)."""
    parts = [FRAME_HEADER.pack(FRAME_MAGIC, frame & 0xFFFFFFFF, len(ids), 22)]
    J = np.ascontiguousarray(joints, dtype="<f4").reshape(len(ids), 66)
    Q = np.ascontiguousarray(quats, dtype="<f4").reshape(len(ids), 88)
    for k, i in enumerate(ids):
        parts += [struct.pack("<I", i), J[k].tobytes(), Q[k].tobytes()]
    return b"".join(parts)


def decode_frame_binary(data: bytes) -> dict:
    magic, frame, n, nj = FRAME_HEADER.unpack_from(data, 0)
    if magic != FRAME_MAGIC or nj != 22 or len(data) != FRAME_HEADER.size + n * AVATAR_RECORD:
        raise ProtocolError("not an AMF1 frame")
    out = {"frame": frame, "avatars": {}}
    off = FRAME_HEADER.size
    for _ in range(n):
        (i,) = struct.unpack_from("<I", data, off)
        J = np.frombuffer(data, "<f4", 66, off + 4).reshape(22, 3)
        Q = np.frombuffer(data, "<f4", 88, off + 4 + 264).reshape(22, 4)
        out["avatars"][i] = {"positions": J, "rotations": Q}
        off += AVATAR_RECORD
    return out


def encode_frame_json(frame: int, ids: list[int], joints: np.ndarray, quats: np.ndarray) -> str:
    return json.dumps({"type": "frame", "frame": frame, "avatars": [
        {"id": i, "positions": np.round(joints[k], 4).tolist(), "rotations": np.round(quats[k], 5).tolist()}
        for k, i in enumerate(ids)]})
