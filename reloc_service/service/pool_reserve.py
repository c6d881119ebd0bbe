"""What a resident map's whole-map pools count against the memory budget before they are made
(:mod:`.residency`). A loaded map's relocalizers make their landmark pools on a thread of
their own after the load (:meth:`~reloc_service.engine.Engine.load`); counting them only
once made let further loads in while they were being built, each map then counting its
keyframes alone (the fleet bench had three 1000-keyframe maps counted in a share that holds
two, its resident memory 4 % over the budget).

So until a map's pools are made it counts, beside its keyframes, a *reserve*: what its pools
will hold once made, and what making them holds on top of that at its peak (the rows being
read; a stored index read into buffers before its arrays are made). The pools scale with the
map's keyframes (a row per landmark observation, about as many per keyframe wherever a map
was made), their making with the pools. The pools' rate per keyframe is measured by every map
whose pools this service made (the largest rate seen; a map denser than those seen is
corrected once its own pools are made, the count then being what they hold), before any by
:data:`POOL_BYTES_PER_KEYFRAME`; the making's peak is :data:`MAKING_PER_POOL_BYTE` times the
pools (the making frees it: the count then drops to what the pools hold).
"""

from __future__ import annotations

import threading

#: Bytes per keyframe the default method's pools hold once made (an ORB and a SIFT pool and
#: their repetition indexes), before this service has measured any: 81.8 MB for the fleet
#: template's 1000 keyframes of 640x480 (``reloc bench --only fleet``; 491 SIFT and 4 ORB
#: landmark observations per keyframe), scripts/pool_build_peak.py.
POOL_BYTES_PER_KEYFRAME = 85_800
#: What making a map's pools holds at its peak beyond what stays once they are made, per byte
#: the pools hold: up to 52.2 MB for the fleet template's 81.8 MB of pools (runs of
#: scripts/pool_build_peak.py: the peak of the resident memory while they were made above it
#: after, the heap trimmed; the peak was 503-505 MB in every run, but what stayed after it
#: was 452 MB in the five runs of its current form and 484-488 MB in four of its first, so
#: 20.3-20.5 MB there: heap the trim could not give back, RssAnon 249 against 218 MB; the
#: larger difference is counted), since a pool's rows are chosen first and read into arrays
#: of their final size.
#: It was 92.0 MB when a pool held every keyframe's features until it was made, then 76-86 MB
#: while its rows were gathered keyframe by keyframe and concatenated.
MAKING_PER_POOL_BYTE = 52.2 / 81.8


class PoolReserve:
    """The bytes a map's pools count until made (see module docstring); the pools' rate per
    keyframe is the largest this service measured, else :data:`POOL_BYTES_PER_KEYFRAME`."""

    def __init__(self, pool_rate: float = POOL_BYTES_PER_KEYFRAME,
                 making_ratio: float = MAKING_PER_POOL_BYTE) -> None:
        if pool_rate < 0 or making_ratio < 0:
            raise ValueError(f"expected bytes per keyframe and a ratio >= 0, got pools "
                             f"{pool_rate}, their making {making_ratio}")
        self._lock = threading.Lock()
        self.pool_rate = float(pool_rate)
        self.making_ratio = float(making_ratio)
        self.measured = 0   # maps whose pools' size set :attr:`pool_rate`

    def pools(self, keyframes: int) -> int:
        """What the pools of a map of ``keyframes`` keyframes will hold once made (bytes)."""
        return int(keyframes * self.pool_rate)

    def making(self, keyframes: int) -> int:
        """What making them holds on top at its peak (bytes)."""
        return int(keyframes * self.pool_rate * self.making_ratio)

    def reserve(self, keyframes: int) -> int:
        """What a map's pools count until they are all made: :meth:`pools` and
        :meth:`making`."""
        return self.pools(keyframes) + self.making(keyframes)

    def learn(self, keyframes: int, held: int) -> None:
        """A map of ``keyframes`` keyframes has made its pools, which hold ``held`` bytes: the
        first measure replaces the prior rate, later ones raise it."""
        if keyframes <= 0 or held <= 0:   # no pools (a method without any), nothing learned
            return
        rate = held / keyframes
        with self._lock:
            self.pool_rate = rate if self.measured == 0 else max(self.pool_rate, rate)
            self.measured += 1
