"""Writes that survive a kill at any instant: the one helper for files and folders.

A file is written whole under a temporary sibling name, then renamed over its target (a rename
within a folder is atomic), so a reader sees the old file or the new one, never half of one.

A folder (a checkpoint, a training state) is filled under `<name>.tmp`, then swapped in: the live
folder is renamed to `<name>.old`, `<name>.tmp` to `<name>`, and `<name>.old` removed. A kill can
land between any two of these steps; `recover_folder`, called before the folder is read, puts back
the newest complete copy (`complete` says what complete means, e.g. a file written last) and
removes the stale ones. The names are fixed (not per process), so the next run finds them.
"""
from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Callable


def write_file(path: str | Path, write: Callable[[Path], None]) -> Path:
    """Call write(tmp) to write the whole file under a temporary sibling name, then rename it over
    `path`. On an error the temporary file is removed and the target is untouched."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def _siblings(folder: Path) -> tuple[Path, Path]:
    return folder.with_name(folder.name + ".tmp"), folder.with_name(folder.name + ".old")


def recover_folder(folder: str | Path, complete: Callable[[Path], bool]) -> Path | None:
    """After a kill during replace_folder: make `folder` the newest complete copy there is and
    remove the stale ones. Returns the folder, or None if no complete copy exists."""
    folder = Path(folder)
    tmp, old = _siblings(folder)
    # newest first: a finished new copy, the live folder, the copy it was replacing
    for candidate in (tmp, folder, old):
        if candidate.exists() and complete(candidate):
            if candidate != folder:
                if folder.exists():
                    shutil.rmtree(folder)
                candidate.rename(folder)
            break
    for stale in (tmp, old):
        if stale.exists():
            shutil.rmtree(stale)
    return folder if folder.exists() and complete(folder) else None


def replace_folder(folder: str | Path, fill: Callable[[Path], None], complete: Callable[[Path], bool]) -> Path:
    """Call fill(tmp) to write the new folder's contents, then swap it in for `folder`; at every
    instant a complete copy (old or new) is on disk under one of the three names."""
    folder = Path(folder)
    tmp, old = _siblings(folder)
    recover_folder(folder, complete)  # a previous kill's leftovers go first
    tmp.mkdir(parents=True)
    fill(tmp)
    if not complete(tmp):
        shutil.rmtree(tmp)
        raise RuntimeError(f"{folder}: the new contents are incomplete; the old folder is kept")
    if folder.exists():
        folder.rename(old)
    tmp.rename(folder)
    if old.exists():
        shutil.rmtree(old)
    return folder
