"""What a map's pools count before they are made (:mod:`reloc_service.service.pool_reserve`):
the pools scale with the keyframes and their making with the pools; the first measure
replaces the prior rate and later ones only raise it."""

from __future__ import annotations

import pytest

from reloc_service.service.pool_reserve import (
    MAKING_PER_POOL_BYTE,
    POOL_BYTES_PER_KEYFRAME,
    PoolReserve,
)


def test_the_reserve_is_the_pools_and_their_making_per_keyframe() -> None:
    reserve = PoolReserve()
    assert reserve.pools(1000) == int(1000 * POOL_BYTES_PER_KEYFRAME)
    assert reserve.making(1000) == int(1000 * POOL_BYTES_PER_KEYFRAME * MAKING_PER_POOL_BYTE)
    assert reserve.reserve(1000) == reserve.pools(1000) + reserve.making(1000)
    assert reserve.reserve(0) == 0


def test_the_first_measure_replaces_the_prior_and_later_ones_raise_it() -> None:
    reserve = PoolReserve(pool_rate=100.0, making_ratio=0.5)
    reserve.learn(1000, 40_000)       # sparser than the prior: replaces it
    assert reserve.pools(1000) == 40_000
    reserve.learn(500, 10_000)        # sparser still: the largest rate seen stays
    assert reserve.pools(1000) == 40_000
    reserve.learn(100, 6_000)         # denser: raises it
    assert reserve.pools(1000) == 60_000
    assert reserve.measured == 3
    reserve.learn(0, 0)               # a map without pools tells nothing
    assert reserve.measured == 3
    assert reserve.making(1000) == 30_000   # the making scales with the pools


def test_negative_rates_are_refused() -> None:
    with pytest.raises(ValueError, match="expected bytes per keyframe and a ratio >= 0"):
        PoolReserve(pool_rate=-1.0)
