"""What a resident map's whole-map pools count against the memory budget before they are made
(:mod:`.residency`). A loaded map's relocalizers make their landmark pools on a thread of
their own after the load (:meth:`~reloc_service.engine.Engine.load`); counting them only
once made let further loads in while they were being built, each map then counting its
keyframes alone (the fleet bench had three 1000-keyframe maps counted in a share that holds
two, its resident memory 4 % over the budget).

So until a map's pools are made it counts, beside its keyframes, a *reserve*: what its pools
will hold once made, and what making one holds on top of that at its peak (the pool's rows
gathered keyframe by keyframe, then concatenated; a stored index read into buffers before its
arrays are made). Both scale with the map's keyframes: the pools hold a row per landmark
observation and a map holds about as many per keyframe wherever it was made. The rates per
keyframe are measured: the pools' final size by every map whose pools this service made (the
largest rate seen; a map denser than those seen is corrected once its own pools are made, the
count then being what they hold), before any by :data:`POOL_BYTES_PER_KEYFRAME`; the making's
peak by :data:`BUILD_BYTES_PER_KEYFRAME` (the making frees it: the count then drops to what
the pools hold).
"""

from __future__ import annotations

import threading

#: Bytes per keyframe the default method's pools hold once made (an ORB and a SIFT pool and
#: their repetition indexes), before this service has measured any: 81.8 MB for the fleet
#: template's 1000 keyframes of 640x480 (``reloc bench --only fleet``; 491 SIFT and 4 ORB
#: landmark observations per keyframe), scripts/pool_build_peak.py.
POOL_BYTES_PER_KEYFRAME = 85_800
#: Bytes per keyframe the making of a map's pools holds at its peak beyond what stays once
#: they are made: 92.0 MB for the fleet template's 1000 keyframes, the peak of the resident
#: memory while they were made above it after (two runs of scripts/pool_build_peak.py, 91.9
#: and 92.0 MB).
BUILD_BYTES_PER_KEYFRAME = 96_400


class PoolReserve:
    """The bytes per keyframe a map's pools count until made (see module docstring); the
    pools' rate is the largest this service measured, else :data:`POOL_BYTES_PER_KEYFRAME`."""

    def __init__(self, pool_rate: float = POOL_BYTES_PER_KEYFRAME,
                 build_rate: float = BUILD_BYTES_PER_KEYFRAME) -> None:
        if pool_rate < 0 or build_rate < 0:
            raise ValueError(f"expected bytes per keyframe >= 0, got pools {pool_rate}, "
                             f"their making {build_rate}")
        self._lock = threading.Lock()
        self.pool_rate = float(pool_rate)
        self.build_rate = float(build_rate)
        self.measured = 0   # maps whose pools' size set :attr:`pool_rate`

    def pools(self, keyframes: int) -> int:
        """What the pools of a map of ``keyframes`` keyframes will hold once made (bytes)."""
        return int(keyframes * self.pool_rate)

    def making(self, keyframes: int) -> int:
        """What making them holds on top at its peak (bytes)."""
        return int(keyframes * self.build_rate)

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
