"""The motion cache: BVH and DeepMimic clips converted once onto the canonical body, one array file per dataset.

A cache file `<name>.npz` holds, concatenated over clips at 30 fps:
    root_pos (N, 3) float32, quats (N, 22, 4) float32, clip_start (C,), clip_len (C,)
and `meta` (JSON): per clip its source path, member key (for incremental imports), source fps,
frames, labels, and the retarget info; plus the skipped files with their reasons.
Writes go through a temporary file and a rename, so an interrupted import never leaves a
half-written cache.
"""
from __future__ import annotations

import hashlib

import json
import os
import re
import sys
import tarfile
import time
import zipfile
import multiprocessing
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..io.atomic import write_file
from ..io import bvh as B
from ..io.bvh import BVHError, read_bvh
from ..io.deepmimic import AXES as DEEPMIMIC_AXES, looks_like_deepmimic, read_deepmimic
from .retarget import resample, retarget

# 2: twist-canonical retargeting; 3: handedness judged per frame (no mirrored sprints); 4: zero-length
# and in-between source bones, leaf bones from ranked children, ignored joints recorded (Bandai
# clips convert as in 3)
CACHE_VERSION = 4
_DEEPMIMIC = "humanoid3d_"
_BANDAI = re.compile(r"dataset-(?P<part>\d+)_(?P<content>[a-z\-]+)_(?P<style>[a-z\-]+)_(?P<id>\d+)$")


class StaleCacheError(ValueError):
    """A cache written by an older importer: import its source again."""


def default_cache_dir() -> Path:
    return Path(os.environ.get("AVATAR_MOTOR_CACHE", Path.home() / ".cache" / "avatar-motor")) / "motion"


def labels_from_name(stem: str) -> dict:
    """Labels from a file name; the Bandai pattern `dataset-N_{content}_{style}_{id}` and
    DeepMimic's `humanoid3d_{content}` are understood."""
    m = _BANDAI.match(stem)
    if m:
        return {"content": m["content"], "style": m["style"]}
    if stem.startswith(_DEEPMIMIC):
        return {"content": stem[len(_DEEPMIMIC):]}
    return {}


def is_held_out(key: str, fraction: float = 0.05) -> bool:
    """The fixed evaluation split: a clip is held out when the SHA-1 of its file name (without
    folders) falls in the lowest `fraction` of the hash range. Stable across machines."""
    h = int(hashlib.sha1(Path(key).name.encode()).hexdigest()[:8], 16)
    return h < fraction * 0x100000000


@dataclass
class MotionCache:
    root_pos: np.ndarray
    quats: np.ndarray
    clip_start: np.ndarray
    clip_len: np.ndarray
    meta: dict
    path: Path | None = None

    @property
    def clips(self) -> list[dict]:
        return self.meta["clips"]

    def clip(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        s, n = int(self.clip_start[i]), int(self.clip_len[i])
        return self.root_pos[s:s + n], self.quats[s:s + n]

    def find(self, query: str) -> int:
        """Index of the clip whose file name contains `query` (exact stem match preferred)."""
        hits = [i for i, c in enumerate(self.clips) if Path(c["key"]).stem == query]
        hits = hits or [i for i, c in enumerate(self.clips) if query in c["key"]]
        if not hits:
            raise KeyError(f"no clip matching {query!r} in {self.path}; try 'avatar-motor data list'")
        return hits[0]

    @staticmethod
    def load(path: str | Path) -> "MotionCache":
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as z:
                meta = json.loads(str(z["meta"]))
                if meta.get("version") == CACHE_VERSION:
                    return MotionCache(z["root_pos"], z["quats"], z["clip_start"], z["clip_len"], meta, path)
        except (OSError, ValueError, KeyError, json.JSONDecodeError) as e:
            raise ValueError(f"{path}: not a readable motion cache ({e}). Delete it and run 'avatar-motor data import' again") from None
        raise StaleCacheError(f"{path}: made by an older importer (cache version {meta.get('version')}, this one writes "
                              f"{CACHE_VERSION}). Run 'avatar-motor data import' on its source again: it converts every file anew")

    def save(self, path: str | Path) -> None:
        def write(tmp: Path) -> None:
            with open(tmp, "wb") as f:
                np.savez(f, root_pos=self.root_pos, quats=self.quats, clip_start=self.clip_start,
                         clip_len=self.clip_len, meta=np.array(json.dumps(self.meta)))

        self.path = write_file(path, write)


def _bounded(key: str, size: int, read) -> bytes:
    """A member's bytes, refused (BVHError) above io.bvh.MAX_BYTES: by its declared size before
    anything is read, and by what it actually yields (a declared size can lie)."""
    if size > B.MAX_BYTES:
        raise BVHError(f"{key}: is {size >> 20} MB, larger than {B.MAX_BYTES >> 20} MB. Split the capture into shorter BVH files")
    data = read(B.MAX_BYTES + 1)
    if len(data) > B.MAX_BYTES:
        raise BVHError(f"{key}: is larger than {B.MAX_BYTES >> 20} MB. Split the capture into shorter BVH files")
    return data


# motion files: BVH, and DeepMimic's JSON clips (.txt as distributed, or .json); a .txt or .json
# that is not a JSON object (a read-me) is passed over without a word (`_is_motion`)
MOTION_SUFFIXES = (".bvh", ".txt", ".json")


def _is_motion(key: str, data: bytes) -> bool:
    """A BVH, or a JSON object with a Frames list (DeepMimic's): a folder's other JSON files, such
    as the Bandai data's per-clip labels beside each BVH, are not motion and are passed over
    (a file given alone is parsed whatever it holds, so its error is the parser's)."""
    return key.lower().endswith(".bvh") or (looks_like_deepmimic(data) and b'"Frames"' in data)


def _iter_sources(src: Path):
    """Yield (key, stamp, load) for each motion file (MOTION_SUFFIXES) in a folder, a file, or a
    .tar(.xz/.gz)/.zip archive (a .whl is a zip: pybullet's carries DeepMimic's clips). Archive
    members are read straight from the archive, one at a time, when load() is called; load raises
    BVHError for a member above the size limit."""
    name = src.name.lower()
    if src.is_dir():
        for p in sorted(src.rglob("*")):
            if p.suffix.lower() in MOTION_SUFFIXES and p.is_file():
                st = p.stat()
                yield str(p.relative_to(src)), f"{st.st_size}:{int(st.st_mtime)}", (lambda p=p: read_file_bounded(p))
    elif name.endswith((".tar", ".tar.xz", ".txz", ".tar.gz", ".tgz", ".tar.bz2")):
        with tarfile.open(src) as tf:
            for mem in tf:
                if mem.isfile() and mem.name.lower().endswith(MOTION_SUFFIXES):
                    yield mem.name, f"{mem.size}:{int(mem.mtime)}", (
                        lambda mem=mem: _bounded(mem.name, mem.size, tf.extractfile(mem).read))
    elif name.endswith((".zip", ".whl")):
        with zipfile.ZipFile(src) as zf:
            for info in zf.infolist():
                if info.filename.lower().endswith(MOTION_SUFFIXES):
                    def load(info=info):
                        with zf.open(info) as f:
                            return _bounded(info.filename, info.file_size, f.read)
                    yield info.filename, f"{info.file_size}:{info.CRC}", load
    elif src.is_file():
        st = src.stat()
        yield src.name, f"{st.st_size}:{int(st.st_mtime)}", (lambda: read_file_bounded(src))
    else:
        raise FileNotFoundError(f"{src}: no such file, folder or archive. Pass a folder of BVH or DeepMimic files, one such "
                                "file, a .tar.xz/.zip of them, or pybullet's wheel")


def read_file_bounded(path: Path) -> bytes:
    with open(path, "rb") as f:
        return _bounded(path.name, path.stat().st_size, f.read)


def convert_clip(key: str, data: bytes, mapping: dict | None = None, unit: str | None = None):
    """BVH or DeepMimic bytes -> (clip arrays, metadata) or (None, reason)."""
    try:
        if looks_like_deepmimic(data):  # axes, unit and ground are the format's own
            b = read_deepmimic(data, name=key)
            r = resample(retarget(b, unit="m", axes=DEEPMIMIC_AXES, ground="source"), 30.0)
        else:
            b = read_bvh(data, name=key)
            r = resample(retarget(b, mapping, unit), 30.0)
    except (BVHError, ValueError) as e:
        return None, str(e)
    if r.root_pos.shape[0] < 2:
        return None, f"{key}: only {r.root_pos.shape[0]} frame after resampling to 30 fps; need at least 2"
    meta = {"key": key, "source_fps": round(b.fps, 4), "source_frames": b.num_frames, "frames": int(r.root_pos.shape[0]),
            "labels": labels_from_name(Path(key).stem),
            "info": {k: (float(v) if isinstance(v, (float, np.floating)) else v) for k, v in r.info.items()}}
    return (r.root_pos, r.quats), meta


class _InProcess:
    """The executor interface, run inline (one worker: no process start-up cost)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def submit(self, fn, *args):
        f = Future()
        f.set_result(fn(*args))
        return f


def _worker_init(parent: int) -> None:
    """parent: the importing process's pid (it may have died while this worker was starting)."""
    import threading

    import torch
    torch.set_num_threads(1)  # one process per core already: more threads only contend

    def watch():  # a killed import must not leave its workers behind (they would idle for minutes)
        while os.getppid() == parent:
            time.sleep(0.5)
        os._exit(1)

    threading.Thread(target=watch, daemon=True).start()


def _convert_job(args):
    key, data, mapping, unit = args
    return key, convert_clip(key, data, mapping, unit)


MAX_PENDING_BYTES = 512 * 1024 * 1024  # member bytes read ahead of the workers at most


def import_motion(src: str | Path, name: str | None = None, cache_dir: str | Path | None = None,
                  workers: int | None = None, mapping: dict | None = None, unit: str | None = None,
                  progress: bool = True, replace: bool = False) -> tuple[Path, dict]:
    """Convert every BVH under `src` into the cache `<cache_dir>/<name>.npz` (incremental: a
    re-import of the same source converts only what changed). A cache of that name imported from
    another source is refused unless `replace`."""
    from tqdm import tqdm

    src = Path(src)
    if name is None:
        name = src.name
        for ext in (".tar.xz", ".tar.gz", ".tar.bz2", ".tgz", ".txz", ".tar", ".zip", ".bvh"):
            if name.lower().endswith(ext):
                name = name[: -len(ext)]
        if name == "data" and src.is_dir():
            name = src.parent.name
        if src.name.lower().startswith("pybullet-") and src.name.lower().endswith(".whl"):
            name = "deepmimic"
    cache_dir = Path(cache_dir) if cache_dir else default_cache_dir()
    path = cache_dir / f"{name}.npz"
    old = None
    if path.exists():
        try:
            old = MotionCache.load(path)
        except StaleCacheError:  # an older importer's conversion: every file is converted anew
            print(f"{path}: written by an older importer; converting every file again", flush=True)
    source = str(src.resolve())
    if old is not None and Path(old.meta.get("source", "")).resolve() != src.resolve():
        if not replace:
            raise FileExistsError(f"{path}: the cache {name!r} was imported from {old.meta.get('source')}; importing "
                                  f"{src} would replace it. Pass --replace to do so, or --name to keep both")
        old = None
    have = {c["key"]: (i, c) for i, c in enumerate(old.clips)} if old else {}
    t0 = time.time()
    kept, new_items, skipped, seen = [], [], [], set()
    workers = workers or min(2, os.cpu_count() or 1)
    alone = src.is_file() and src.suffix.lower() in MOTION_SUFFIXES  # one motion file, not an archive

    def jobs():
        for key, stamp, load in _iter_sources(src):
            seen.add(key)
            if key in have and have[key][1].get("stamp") == stamp:
                kept.append(have[key][0])
                continue
            try:
                data = load()
            except BVHError as e:
                skipped.append({"key": key, "reason": str(e)})
                continue
            if not (alone or _is_motion(key, data)):
                continue
            yield key, stamp, data

    stamps = {}
    # into a log file (not a terminal) a progress line every 10 s, not ten a second
    bar = tqdm(desc=f"import {name}", unit="clip", disable=not progress, mininterval=0.1 if sys.stderr.isatty() else 10)
    # spawn, not fork: a forked child of a process whose torch thread pool already ran can deadlock
    pool = (ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"), initializer=_worker_init, initargs=(os.getpid(),))
            if workers > 1 else _InProcess())
    with pool:
        pending = []  # (future, bytes read for it)

        def drain(limit, byte_limit=MAX_PENDING_BYTES):
            while len(pending) > limit or sum(n for _, n in pending) > byte_limit:
                key, (res, meta) = pending.pop(0)[0].result()
                bar.update(1)
                if res is None:
                    skipped.append({"key": key, "reason": meta})
                else:
                    meta["stamp"] = stamps[key]
                    new_items.append((res, meta))

        for key, stamp, data in jobs():
            stamps[key] = stamp
            pending.append((pool.submit(_convert_job, (key, data, mapping, unit)), len(data)))
            del data
            drain(4 * workers)
        drain(0)
    bar.close()
    # assemble: kept old clips + new ones, in key order
    items = []
    for i in kept:
        rp, q = old.clip(i)
        items.append(((rp, q), old.clips[i]))
    items.extend(new_items)
    items.sort(key=lambda it: it[1]["key"])
    if not items:
        raise ValueError(f"{src}: no clip could be imported ({len(skipped)} skipped"
                         + (f", first reason: {skipped[0]['reason']}" if skipped else ", no motion files (.bvh, DeepMimic .txt) found") + ")")
    lens = np.array([it[0][0].shape[0] for it in items], np.int64)
    meta = {"version": CACHE_VERSION, "name": name, "source": source, "fps": 30.0,
            "clips": [it[1] for it in items], "skipped": skipped}
    cache = MotionCache(np.concatenate([it[0][0] for it in items]), np.concatenate([it[0][1] for it in items]),
                        np.concatenate(([0], np.cumsum(lens)[:-1])), lens, meta)
    cache.save(path)
    summary = summarize(cache)
    summary.update({"new": len(new_items), "unchanged": len(kept), "skipped": skipped, "seconds": time.time() - t0, "path": str(path)})
    return path, summary


def summarize(cache: MotionCache) -> dict:
    labels: dict[str, dict[str, int]] = {}
    for c in cache.clips:
        for k, v in c["labels"].items():
            labels.setdefault(k, {})
            labels[k][v] = labels[k].get(v, 0) + 1
    frames = int(cache.clip_len.sum())
    namings: dict[str, int] = {}
    ignored: dict[str, set] = {}  # per naming, the source joints no canonical joint takes
    for c in cache.clips:
        info = c.get("info", {})
        naming = info.get("skeleton", "?")
        namings[naming] = namings.get(naming, 0) + 1
        ignored.setdefault(naming, set()).update(info.get("ignored", []))
    return {"clips": len(cache.clips), "frames": frames, "minutes": frames / 30.0 / 60.0, "labels": labels,
            "namings": namings, "ignored": ignored}


def format_summary(s: dict) -> str:
    head = f"{s['path']}: {s['clips']} clips"
    if "new" in s:
        head += f" ({s['new']} new, {s['unchanged']} unchanged)"
    head += f", {s['frames']} frames = {s['minutes']:.1f} min ({s['minutes'] / 60:.2f} h) at 30 fps"
    if "seconds" in s:
        head += f", imported in {s['seconds']:.1f} s"
    lines = [head]
    if s.get("namings"):
        lines.append("  skeleton naming detected: " + ", ".join(f"{n} ({v} clips)" for n, v in sorted(s["namings"].items())))
    for naming, names in sorted((s.get("ignored") or {}).items()):
        if names:
            names = sorted(names)
            lines.append(f"  {naming}: source joints ignored ({len(names)}): " + ", ".join(names[:40]) + (" ..." if len(names) > 40 else ""))
    for k, counts in s["labels"].items():
        lines.append(f"  {k}: " + ", ".join(f"{v} {n}" for v, n in sorted(counts.items(), key=lambda kv: -kv[1])))
    sk = s.get("skipped", [])
    lines.append(f"  skipped: {len(sk)}")
    for x in sk:
        lines.append(f"    {x['reason']}")
    return "\n".join(lines)


def list_caches(cache_dir: str | Path | None = None) -> list[Path]:
    d = Path(cache_dir) if cache_dir else default_cache_dir()
    return sorted(p for p in d.glob("*.npz") if not p.name.endswith(".stats.npz"))
