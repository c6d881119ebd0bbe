"""The process's open-file limit, raised to what the served maps need.

A served map keeps two files open (its journal segment and its lock), and Zenoh, the worker
processes and the logs take some more. systemd starts services with a soft limit of 1024 and
a hard limit far above it (524288 since systemd 240); the soft limit is only a default a
process may raise itself up to the hard one (Go's runtime does so at start). ``reloc serve``
raises it at start, to the hard limit capped at :data:`WANTED`, and says so; where even the
hard limit cannot hold ``quotas.max_maps`` maps it warns with the numbers and the fix.
"""

from __future__ import annotations

import logging
import resource
from dataclasses import dataclass

log = logging.getLogger(__name__)

#: Open files per served map: its journal segment and its lock file.
FILES_PER_MAP = 2
#: Open files the rest of the service takes (Zenoh's sockets, worker pipes, logs, imports).
BASE_FILES = 256
#: The soft limit asked for: enough for thousands of maps, small enough for any kernel.
WANTED = 65536


@dataclass(frozen=True)
class OpenFiles:
    """The open-file limit before and after :func:`raise_limit`, and what the maps need."""

    soft_before: int
    soft: int
    hard: int
    needed: int

    @property
    def enough(self) -> bool:
        return self.soft >= self.needed


def needed_for(max_maps: int) -> int:
    """Open files a service serving ``max_maps`` maps may hold."""
    return BASE_FILES + FILES_PER_MAP * max_maps


def raise_limit(max_maps: int) -> OpenFiles:
    """Raise the soft RLIMIT_NOFILE towards the hard limit (at most :data:`WANTED`); log the
    change, and a warning when the result cannot hold ``max_maps`` maps."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    target = WANTED if hard == resource.RLIM_INFINITY else min(hard, WANTED)
    new = soft
    if soft != resource.RLIM_INFINITY and soft < target:
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
            new = target
            log.info("open files: soft limit raised from %d to %d (hard limit %s)", soft, new,
                     "unlimited" if hard == resource.RLIM_INFINITY else hard)
        except (ValueError, OSError) as exc:
            log.warning("open files: could not raise the soft limit %d to %d: %s", soft,
                        target, exc)
    result = OpenFiles(soft, new, hard, needed_for(max_maps))
    if not result.enough:
        log.warning("open files: the limit %d cannot hold quotas.max_maps = %d maps (about %d "
                    "files: %d per map + %d); raise LimitNOFILE in the systemd unit (or "
                    "`ulimit -n` before reloc serve) or lower quotas.max_maps", result.soft,
                    max_maps, result.needed, FILES_PER_MAP, BASE_FILES)
    return result
