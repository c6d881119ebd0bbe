"""The private directories where a service with worker processes saves the replica bases its
workers load (:mod:`.processes`), and the removal of those a killed service left behind."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

#: Prefix of the private directory of a service's replica bases, followed by its pid.
SCRATCH_PREFIX = "reloc-replicas-"


def remove_stale_scratch(tmp: Path) -> list[Path]:
    """Remove the replica directories of services that are gone (killed -9: no ``close``),
    so a service restarted after crashes does not fill the disk; returns what was removed.
    A directory counts as stale when the pid in its name no longer runs."""
    removed = []
    for path in tmp.glob(f"{SCRATCH_PREFIX}*-*"):
        pid = path.name[len(SCRATCH_PREFIX):].split("-", 1)[0]
        if pid.isdigit() and not _alive(int(pid)) and path.is_dir():
            shutil.rmtree(path, ignore_errors=True)
            removed.append(path)
    return removed


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process: alive, not ours to judge
        return True
    return True
