"""The limit of the work itself, which every latency is compared with: decoding the query
image and extracting its features, timed on the same queries in the same run (so machine
load hits the limit and the methods alike)."""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import numpy.typing as npt

from ...core.features import FeatureConf, extract
from .samples import pct_ms

#: ORB features of the limit the default method is held to on the datasets: ORB-SLAM's
#: budget for a 640x480 frame, twice what the fast path extracts.
LIMIT_ORB_FEATURES = 1000


def measure_limit(decode: Callable[[], npt.NDArray[np.uint8]], out: dict[str, list[float]],
                  counts: Mapping[str, int]) -> None:
    """Append to ``out`` the seconds of ``decode()`` (``out["decode"]``) and of extracting
    ``counts[kind]`` features of each kind from the image it returns (``out[kind]``)."""
    start = time.perf_counter()
    image = decode()
    out.setdefault("decode", []).append(time.perf_counter() - start)
    for kind, n in counts.items():
        start = time.perf_counter()
        extract(image, FeatureConf(kind=kind, max_features=n))
        out.setdefault(kind, []).append(time.perf_counter() - start)


def limit_summary(limit: Mapping[str, list[float]]) -> dict[str, float]:
    """p50 of decoding, and per feature kind of extraction alone and of decode + extraction
    (p50 and p99 of the per-query sums), in milliseconds."""
    decode = np.asarray(limit["decode"])
    out = {"decode_p50_ms": pct_ms(limit["decode"], 50)}
    for kind in (k for k in limit if k != "decode"):
        total = list(decode + np.asarray(limit[kind]))
        out[f"{kind}_p50_ms"] = pct_ms(limit[kind], 50)
        out[f"{kind}_limit_p50_ms"] = pct_ms(total, 50)
        out[f"{kind}_limit_p99_ms"] = pct_ms(total, 99)
    return out


def over_limit(results: Mapping[str, Any], limit: Mapping[str, float], kind: str = "orb"
               ) -> dict[str, float | None]:
    """Each column's p50 latency over the decode + ``kind`` limit's p50 (None for a column
    that failed or has no latency)."""
    bound = limit.get(f"{kind}_limit_p50_ms")
    return {column: (r["p50_ms"] / bound if bound and r.get("p50_ms") is not None else None)
            for column, r in results.items() if "error" not in r}
