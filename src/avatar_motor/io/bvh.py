"""BVH reader and writer: any hierarchy, any channel order, position channels on any joint,
End Sites, any frame time. Values stay in the file's own units and axes; unit and axis detection
live in `io/units.py` and are applied by the importer.

Every problem raises `BVHError` naming the file, what is wrong and how to fix it.
"""
from __future__ import annotations

import io as _io
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..body import rotations as rot
from .atomic import write_file

ROTATION_CHANNELS = ("Xrotation", "Yrotation", "Zrotation")
POSITION_CHANNELS = ("Xposition", "Yposition", "Zposition")
MAX_JOINTS = 1024
# sizes refused before anything is read or allocated: a BVH above MAX_BYTES (a 20-minute 120-fps
# capture of 70 joints is ~250 MB; Bandai's clips are ~1 MB) or with a motion of more values than
# MAX_VALUES (2 GB as float64); the hierarchy must end within MAX_HIERARCHY_BYTES
MAX_BYTES = 256 * 1024 * 1024
MAX_VALUES = 256 * 1024 * 1024
MAX_HIERARCHY_BYTES = 4 * 1024 * 1024
_MOTION = re.compile(r"^[ \t]*MOTION\b", re.M | re.I)
MIN_FRAME_TIME, MAX_FRAME_TIME = 1e-4, 1.0  # 10 kHz .. 1 Hz


class BVHError(ValueError):
    """A BVH file could not be read; the message names the file, the problem and the fix."""


@dataclass
class BVH:
    names: list[str]
    parents: list[int]
    offsets: np.ndarray  # (J, 3) float64, file units
    channels: list[list[str]]  # per joint, in file order
    motion: np.ndarray  # (F, C) float64; C = total channel count; angles in degrees
    frame_time: float
    end_sites: dict[int, np.ndarray] = field(default_factory=dict)  # joint -> (3,) offset
    source: str = "<memory>"

    @property
    def num_frames(self) -> int:
        return self.motion.shape[0]

    @property
    def fps(self) -> float:
        return 1.0 / self.frame_time

    def channel_slices(self) -> list[slice]:
        out, c = [], 0
        for ch in self.channels:
            out.append(slice(c, c + len(ch)))
            c += len(ch)
        return out

    def local_rotations(self) -> torch.Tensor:
        """(F, J, 3, 3) float64 local rotation matrices from the Euler channels."""
        F, J = self.num_frames, len(self.names)
        R = torch.eye(3, dtype=torch.float64).repeat(F, J, 1, 1)
        m = torch.from_numpy(self.motion)
        for j, (ch, sl) in enumerate(zip(self.channels, self.channel_slices())):
            cols = [k for k, c in enumerate(ch) if c in ROTATION_CHANNELS]
            if not cols:
                continue
            order = "".join(ch[k][0] for k in cols)
            ang = torch.deg2rad(m[:, sl][:, cols])
            if len(cols) == 3:
                R[:, j] = rot.euler_to_matrix(ang, order)
            else:  # fewer than 3 rotation channels: compose those present
                Rj = torch.eye(3, dtype=torch.float64).repeat(F, 1, 1)
                for a, k in zip(order, range(len(cols))):
                    Rj = Rj @ rot._axis_matrix(a, ang[:, k])
                R[:, j] = Rj
        return R

    def local_translations(self) -> np.ndarray:
        """(F, J, 3) local translations: position channels where present, the OFFSET otherwise."""
        F, J = self.num_frames, len(self.names)
        t = np.broadcast_to(self.offsets, (F, J, 3)).copy()
        for j, (ch, sl) in enumerate(zip(self.channels, self.channel_slices())):
            block = self.motion[:, sl]
            for k, c in enumerate(ch):
                if c in POSITION_CHANNELS:
                    t[:, j, POSITION_CHANNELS.index(c)] = block[:, k]
        return t

    def global_transforms(self) -> tuple[np.ndarray, np.ndarray]:
        """World positions (F, J, 3) and rotations (F, J, 3, 3), file units and axes."""
        R = self.local_rotations().numpy()
        t = self.local_translations()
        G = np.empty_like(R)
        P = np.empty_like(t)
        for j, p in enumerate(self.parents):
            if p < 0:
                G[:, j], P[:, j] = R[:, j], t[:, j]
            else:
                G[:, j] = G[:, p] @ R[:, j]
                P[:, j] = P[:, p] + np.einsum("fab,fb->fa", G[:, p], t[:, j])
        return P, G

    def children(self, j: int) -> list[int]:
        return [k for k, p in enumerate(self.parents) if p == j]


_NUM = re.compile(r"^[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$")


def _fail(src: str, problem: str, fix: str) -> BVHError:
    return BVHError(f"{src}: {problem}. {fix}")


def read_bvh(path_or_bytes: str | Path | bytes, name: str | None = None) -> BVH:
    """Read a BVH from a path or from bytes (e.g. an archive member; pass `name` for messages)."""
    if isinstance(path_or_bytes, (bytes, bytearray)):
        raw, src = bytes(path_or_bytes), name or "<bytes>"
    else:
        src = name or str(path_or_bytes)
        try:
            with open(path_or_bytes, "rb") as f:
                raw = f.read(MAX_BYTES + 1)
        except OSError as e:
            raise _fail(src, f"cannot be opened ({e.strerror})", "Check the path and permissions") from None
    if len(raw) > MAX_BYTES:
        raise _fail(src, f"is larger than {MAX_BYTES >> 20} MB", "Split the capture into shorter BVH files")
    if b"\x00" in raw[:4096]:
        raise _fail(src, "is binary, not a BVH text file", "Pass a BVH motion file (text starting with HIERARCHY)")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        text = raw.decode("latin-1")
    return parse_bvh(text, src)


def _lines(text: str, pos: int):
    """The lines of text from pos on, one at a time (a StringIO would copy the text at 4 bytes a character)."""
    while pos < len(text):
        end = text.find("\n", pos)
        end = len(text) if end < 0 else end
        yield text[pos:end]
        pos = end + 1


def parse_bvh(text: str, src: str = "<string>") -> BVH:
    if "\r" in text[:MAX_HIERARCHY_BYTES] and "\n" not in text[:MAX_HIERARCHY_BYTES]:
        text = text.replace("\r", "\n")  # classic Mac line endings
    found = _MOTION.search(text, 0, MAX_HIERARCHY_BYTES)
    lines = text[:found.start() if found else MAX_HIERARCHY_BYTES].splitlines()  # the hierarchy only
    tokens: list[tuple[str, int]] = []
    for ln, line in enumerate(lines, 1):
        tokens.extend((tok, ln) for tok in line.replace("{", " { ").replace("}", " } ").split())
    if not tokens or tokens[0][0].upper() != "HIERARCHY":
        raise _fail(src, "does not start with HIERARCHY", "Pass a BVH motion file; this one is empty or another format")
    if found is None:
        more = len(text) > MAX_HIERARCHY_BYTES
        raise _fail(src, f"has no MOTION section{f' within its first {MAX_HIERARCHY_BYTES >> 20} MB' if more else ''} "
                    "(file truncated?)", "Re-export the complete file")

    names: list[str] = []
    parents: list[int] = []
    offsets: list[list[float]] = []
    channels: list[list[str]] = []
    end_sites: dict[int, np.ndarray] = {}
    pos = 1
    stack: list[int] = []  # joint index, or -2 for an End Site block

    def tok(what: str) -> tuple[str, int]:
        nonlocal pos
        if pos >= len(tokens):
            raise _fail(src, f"hierarchy ends early while reading {what}", "The HIERARCHY block is truncated; re-export the file")
        t = tokens[pos]
        pos += 1
        return t

    def number(what: str) -> float:
        t, ln = tok(what)
        if not _NUM.match(t):
            raise _fail(src, f"line {ln}: {what} must be a number, got {t!r}", "Fix or re-export the file")
        return float(t)

    pending_end = False
    while pos < len(tokens):
        t, ln = tok("a joint")
        key = t.upper()
        if key in ("ROOT", "JOINT"):
            if key == "ROOT" and (stack or names):
                raise _fail(src, f"line {ln}: more than one ROOT", "Keep one skeleton per file")
            if key == "JOINT" and not stack:
                raise _fail(src, f"line {ln}: JOINT outside any parent", "Check the braces of the hierarchy")
            jname, _ = tok("a joint name")
            if jname in names:
                raise _fail(src, f"line {ln}: joint name {jname!r} appears twice (cyclic or duplicated hierarchy)", "Give every joint a unique name")
            parent = stack[-1] if stack else -1
            if parent == -2:
                raise _fail(src, f"line {ln}: joint inside an End Site", "End Sites cannot have children")
            names.append(jname)
            parents.append(parent)
            offsets.append([0.0, 0.0, 0.0])
            channels.append([])
            if len(names) > MAX_JOINTS:
                raise _fail(src, f"more than {MAX_JOINTS} joints", "This is not a body skeleton; check the file")
            if tok("'{'")[0] != "{":
                raise _fail(src, f"line {ln}: expected '{{' after joint {jname}", "Fix the hierarchy braces")
            stack.append(len(names) - 1)
        elif key == "END":
            site, _ = tok("Site")
            if site.upper() != "SITE" or not stack or stack[-1] < 0:
                raise _fail(src, f"line {ln}: misplaced End Site", "Fix the hierarchy")
            if tok("'{'")[0] != "{":
                raise _fail(src, f"line {ln}: expected '{{' after End Site", "Fix the hierarchy braces")
            pending_end = True
            stack.append(-2)
        elif key == "OFFSET":
            if not stack:
                raise _fail(src, f"line {ln}: OFFSET outside a joint", "Fix the hierarchy")
            v = [number("OFFSET value") for _ in range(3)]
            if stack[-1] == -2:
                end_sites.setdefault(stack[-2], [])
                end_sites[stack[-2]].append(v)
            else:
                offsets[stack[-1]] = v
        elif key == "CHANNELS":
            if not stack or stack[-1] < 0:
                raise _fail(src, f"line {ln}: CHANNELS outside a joint", "Fix the hierarchy")
            n = number("channel count")
            if n != int(n) or not 0 <= n <= 6:
                raise _fail(src, f"line {ln}: channel count {n} is not 0..6", "Fix the CHANNELS line")
            chs = [tok("a channel name")[0] for _ in range(int(n))]
            for c in chs:
                if c not in ROTATION_CHANNELS + POSITION_CHANNELS:
                    raise _fail(src, f"line {ln}: unknown channel {c!r}", "Channels are X/Y/Z position and rotation")
            channels[stack[-1]] = chs
        elif key == "}":
            if not stack:
                raise _fail(src, f"line {ln}: unbalanced '}}'", "Fix the hierarchy braces")
            stack.pop()
        else:
            raise _fail(src, f"line {ln}: unexpected token {t!r} in the hierarchy", "Fix or re-export the file")
    del pending_end
    if stack:
        raise _fail(src, "hierarchy braces are not closed", "The HIERARCHY block is truncated; re-export the file")
    if not names:
        raise _fail(src, "hierarchy has no joints", "Pass a BVH with a ROOT joint")

    # ---- MOTION, read lazily: the rows are streamed to the parser and nothing past the last
    # declared frame is looked at (trailing garbage costs nothing)
    nl = text.find("\n", found.end())  # the rest of the MOTION line is skipped
    body = _lines(text, nl + 1 if nl >= 0 else len(text))
    header: dict[str, str] = {}
    while len(header) < 2:
        line = next(body, None)
        if line is None:
            break
        line = line.strip()
        if not line:
            continue
        head, _, val = line.partition(":")
        header[head.strip().lower()] = val.strip()
    if "frames" not in header or "frame time" not in header:
        raise _fail(src, "MOTION section lacks 'Frames:' or 'Frame Time:'", "Re-export the complete file")
    try:
        n_frames = int(header["frames"])
        frame_time = float(header["frame time"])
    except ValueError:
        raise _fail(src, f"bad MOTION header (Frames: {header['frames']!r}, Frame Time: {header['frame time']!r})", "Frames must be an integer and Frame Time seconds per frame") from None
    if n_frames <= 0:
        raise _fail(src, f"has {n_frames} frames", "Export at least one frame of motion")
    if not (MIN_FRAME_TIME <= frame_time <= MAX_FRAME_TIME) or not math.isfinite(frame_time):
        raise _fail(src, f"frame time {frame_time} s is absurd (expected {MIN_FRAME_TIME}..{MAX_FRAME_TIME})", "Fix 'Frame Time:' (e.g. 0.0333333 for 30 fps)")
    n_ch = sum(len(c) for c in channels)
    if n_frames * max(n_ch, 1) > MAX_VALUES:
        raise _fail(src, f"declares {n_frames} frames of {n_ch} channels, more than {MAX_VALUES >> 20} M values",
                    "Fix 'Frames:' or split the capture into shorter files")
    if 2 * n_frames * max(n_ch, 1) > len(text) - found.end():  # every value needs a digit and a separator
        raise _fail(src, f"motion is truncated: header says {n_frames} frames, the file is too short for them",
                    "Re-export the file or fix 'Frames:'")
    try:  # blank lines are skipped and not counted
        motion = np.loadtxt(body, dtype=np.float64, ndmin=2, max_rows=n_frames)
    except ValueError as e:
        msg = str(e).splitlines()[0]
        raise _fail(src, f"motion data is not numeric or rows differ in length ({msg})", f"Every frame row needs {n_ch} numbers") from None
    if len(motion) < n_frames:
        raise _fail(src, f"motion is truncated: header says {n_frames} frames, found {len(motion)}", "Re-export the file or fix 'Frames:'")
    if motion.shape[1] != n_ch:
        raise _fail(src, f"wrong channel count: frames have {motion.shape[1]} values, hierarchy declares {n_ch}", "Fix the CHANNELS lines or the motion rows")
    if not np.isfinite(motion).all():
        raise _fail(src, "motion contains NaN or infinite values", "Clean the capture before importing")
    return BVH(names, parents, np.asarray(offsets, np.float64), channels, motion, frame_time,
               {j: np.asarray(v[0], np.float64) for j, v in end_sites.items()}, src)


def dfs_order(parents: list[int]) -> list[int]:
    """Joint indices in the depth-first order a BVH file lists them."""
    roots = [j for j, p in enumerate(parents) if p < 0]
    if len(roots) != 1:
        raise ValueError(f"a BVH needs exactly one root joint, got {len(roots)}")
    order, stack = [], [roots[0]]
    while stack:
        j = stack.pop()
        order.append(j)
        stack.extend(reversed([k for k, p in enumerate(parents) if p == j]))
    return order


def format_bvh(b: BVH, precision: int = 6) -> str:
    """Text of a BVH. Joints are written depth-first (as the format requires) and the motion
    columns are reordered to match, so any joint order in memory round-trips."""
    order = dfs_order(b.parents)
    out = ["HIERARCHY"]
    fmt = lambda v: " ".join(f"{x:.{precision}f}" for x in v)  # noqa: E731

    def emit(j: int, depth: int) -> None:
        ind = "  " * depth
        out.append(f"{ind}{'ROOT' if b.parents[j] < 0 else 'JOINT'} {b.names[j]}")
        out.append(f"{ind}{{")
        out.append(f"{ind}  OFFSET {fmt(b.offsets[j])}")
        out.append(f"{ind}  CHANNELS {len(b.channels[j])} {' '.join(b.channels[j])}".rstrip())
        kids = b.children(j)
        for c in kids:
            emit(c, depth + 1)
        if not kids or j in b.end_sites:
            out.append(f"{ind}  End Site")
            out.append(f"{ind}  {{")
            out.append(f"{ind}    OFFSET {fmt(b.end_sites.get(j, np.zeros(3)))}")
            out.append(f"{ind}  }}")
        out.append(f"{ind}}}")

    emit(order[0], 0)
    slices = b.channel_slices()
    motion = np.concatenate([b.motion[:, slices[j]] for j in order], 1) if b.motion.size else b.motion
    out += ["MOTION", f"Frames: {b.num_frames}", f"Frame Time: {b.frame_time:.8f}"]
    buf = _io.StringIO()
    np.savetxt(buf, motion, fmt=f"%.{precision}f", delimiter=" ")
    return "\n".join(out) + "\n" + buf.getvalue()


def write_bvh(path: str | Path, b: BVH, precision: int = 6) -> None:
    """Write atomically (io/atomic.py)."""
    write_file(path, lambda tmp: tmp.write_text(format_bvh(b, precision)))


def bvh_from_rotations(names: list[str], parents: list[int], offsets: np.ndarray, root_pos: np.ndarray,
                       local_rot: torch.Tensor, frame_time: float, order: str = "ZXY",
                       end_sites: dict[int, np.ndarray] | None = None,
                       positions: dict[int, np.ndarray] | None = None) -> BVH:
    """Build a BVH with root position channels + `order` rotation channels on every joint.

    root_pos (F, 3) in file units; local_rot (F, J, 3, 3) including the root's rotation;
    positions: per-frame local translations (F, 3) of other joints that get position channels
    (e.g. a pelvis below a ground-level root joint)."""
    ang = torch.rad2deg(rot.matrix_to_euler(local_rot.double(), order)).numpy()
    F, J = ang.shape[:2]
    positions = {j: v for j, v in (positions or {}).items() if parents[j] >= 0}
    positions.update({j: root_pos for j, p in enumerate(parents) if p < 0})
    rch = [f"{a}rotation" for a in order]
    channels = [list(POSITION_CHANNELS) + rch if j in positions else list(rch) for j in range(J)]
    cols = []
    for j in range(J):
        if j in positions:
            cols.append(positions[j])
        cols.append(ang[:, j])
    return BVH(list(names), list(parents), np.asarray(offsets, np.float64), channels,
               np.concatenate(cols, 1), frame_time, dict(end_sites or {}))
