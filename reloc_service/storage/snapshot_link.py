"""A loaded snapshot handed on as it is: another map directory whose current snapshot is the
same files, hard-linked (no byte copied or rewritten: a snapshot's files are never changed
once written, and a link outlives the pruning of the original). A replica of a map that has
not changed since it was loaded reads it from there instead of a fresh save of the map (which
writes every keyframe again: seconds for 1000 keyframes)."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from .snapshot_files import CURRENT_FILE


def link_snapshot(snapshot: Path, target: Path) -> bool:
    """Make ``target`` (a new or empty directory) a map directory whose current snapshot
    holds hard links to the files of ``snapshot`` (``<map>/snapshots/<n>``); False, with
    ``target`` left empty, where a link cannot be made (another file system, the snapshot
    pruned meanwhile)."""
    relative = snapshot.relative_to(snapshot.parent.parent)
    try:
        shutil.copytree(snapshot, target / relative, copy_function=os.link)
    except (OSError, shutil.Error):
        _empty(target)
        return False
    (target / CURRENT_FILE).write_text(relative.as_posix() + "\n")
    return True


def copy_tree_keeping_links(source: Path, target: Path) -> None:
    """Copy directory ``source`` to ``target`` (which must not exist) with files that are
    hard links to one another in ``source`` hard links to one another in ``target`` too (a
    snapshot's model file shared by two methods stays one file on disk)."""
    copied: dict[tuple[int, int], str] = {}

    def copy(src: str, dst: str) -> str:
        st = os.stat(src)
        key = (st.st_dev, st.st_ino)
        if st.st_nlink > 1 and key in copied:
            os.link(copied[key], dst)
        else:
            shutil.copy2(src, dst)
            copied[key] = dst
        return dst

    shutil.copytree(source, target, copy_function=copy)


def _empty(directory: Path) -> None:
    for child in directory.iterdir() if directory.is_dir() else []:
        if child.is_dir():
            shutil.rmtree(child, ignore_errors=True)
        else:
            child.unlink(missing_ok=True)
