"""The thesis's evaluation figures as PNGs: a top view of ground-truth vs found positions
(figures 5.2a-5.17a), the translation error histogram with its mean (5.2b-5.17b) and the
histogram of the rank of the chosen keyframe among the closest ones (figure 3.2).

matplotlib is an optional dependency (``pip install reloc[plots]``), imported only here and
only when a plot is drawn; figures are drawn without pyplot (no global state, no display).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ...core.errors import ConfigError

if TYPE_CHECKING:
    from .results import EvalResult, MapInfo, MethodResult

_AXES = "xyz"


def _figure(width: float = 6.4, height: float = 4.8) -> Any:
    try:
        from matplotlib.figure import Figure
    except ImportError:
        raise ConfigError("plots need matplotlib: pip install reloc[plots]") from None
    return Figure(figsize=(width, height), dpi=100, layout="constrained")


def method_slug(method: str) -> str:
    """A file-name-safe form of a method string (``"bow+p3p,sbi+esm"`` -> ``"bow-p3p_sbi-esm"``)."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", method.replace("+", "-")).strip("_") or "method"


def plot_axes(points_world: np.ndarray) -> tuple[int, int]:
    """The two world axes (indices, ascending) along which ``points_world`` (N, 3) spread most."""
    extent = np.ptp(np.asarray(points_world, dtype=np.float64).reshape(-1, 3), axis=0)
    a, b = sorted(np.argsort(-extent, kind="stable")[:2].tolist())
    return int(a), int(b)


def plot_top_view(method: MethodResult, map_info: MapInfo, path: str | Path) -> Path:
    """Ground-truth query positions (blue), found positions (green), their error segments (red),
    queries with no pose (black x) and the map keyframes (grey triangles), on the two axes of
    largest extent."""
    gt = np.array([q.gt_world_from_cam[:3] for q in method.queries]).reshape(-1, 3)
    found = [(i, q.est_world_from_cam[:3]) for i, q in enumerate(method.queries)
             if q.est_world_from_cam is not None]
    kf = np.array(map_info.keyframe_positions_world, dtype=np.float64).reshape(-1, 3)
    a, b = plot_axes(np.vstack([gt, kf]))
    fig = _figure()
    ax = fig.add_subplot()
    ax.scatter(kf[:, a], kf[:, b], s=36, marker="^", facecolors="none", edgecolors="0.45",
               zorder=4, label="map keyframes")
    ax.plot(gt[:, a], gt[:, b], ".-", color="tab:blue", lw=0.8, ms=5, label="ground truth")
    lost = np.array([q.est_world_from_cam is None for q in method.queries], dtype=bool)
    if lost.any():
        ax.scatter(gt[lost, a], gt[lost, b], s=30, marker="x", color="black", zorder=5,
                   label="not relocalized")
    if found:
        idx = np.array([i for i, _ in found])
        est = np.array([p for _, p in found])
        seg_x = np.stack([gt[idx, a], est[:, a]])
        seg_y = np.stack([gt[idx, b], est[:, b]])
        ax.plot(seg_x, seg_y, "-", color="tab:red", lw=0.8)
        ax.plot([], [], "-", color="tab:red", lw=0.8, label="error")
        ax.scatter(est[:, a], est[:, b], s=12, color="tab:green", zorder=3, label="found")
    s = method.summary
    ax.set_title(f"{method.method}: {s.relocalized}/{s.queries} relocalized")
    ax.set_xlabel(f"{_AXES[a]} (m)")
    ax.set_ylabel(f"{_AXES[b]} (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, lw=0.3)
    ax.legend(fontsize="small", loc="best")
    return _save(fig, path)


def plot_error_histogram(method: MethodResult, path: str | Path, bins: int = 20) -> Path:
    """Histogram of the translation errors (m) of the returned poses, mean as a red line."""
    errors = np.array([q.t_err_m for q in method.queries if q.t_err_m is not None])
    fig = _figure()
    ax = fig.add_subplot()
    if len(errors):
        ax.hist(errors, bins=bins, color="tab:blue", edgecolor="white")
        mean = float(errors.mean())
        ax.axvline(mean, color="red", lw=1.5, label=f"mean {mean:.3f} m")
        ax.legend(fontsize="small")
    else:
        ax.text(0.5, 0.5, "no pose returned", ha="center", va="center", transform=ax.transAxes)
    ax.set_title(f"{method.method}: translation error, {len(errors)}/{len(method.queries)} "
                 "returned")
    ax.set_xlabel("translation error (m)")
    ax.set_ylabel("queries")
    _integer_y(ax)
    return _save(fig, path)


def plot_rank_histogram(method: MethodResult, path: str | Path) -> Path:
    """How often the chosen keyframe was the k-th closest to the query (thesis figure 3.2)."""
    hist = method.summary.rank_histogram
    fig = _figure()
    ax = fig.add_subplot()
    if hist:
        ks = np.arange(1, max(hist) + 1)
        ax.bar(ks, [hist.get(int(k), 0) for k in ks], color="tab:blue", width=0.8)
        ax.set_xticks(ks if len(ks) <= 20 else ks[:: int(np.ceil(len(ks) / 20))])
    ax.set_title(f"{method.method}: rank of the chosen keyframe among the closest")
    ax.set_xlabel("k (1 = the ground-truth closest keyframe)")
    ax.set_ylabel("queries")
    _integer_y(ax)
    return _save(fig, path)


def plot_result(result: EvalResult, out_dir: str | Path) -> list[Path]:
    """Every figure of every method into ``out_dir`` (created); returns the PNG paths. The
    rank histogram is drawn for methods whose results name matched keyframes."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for m in result.methods:
        slug = method_slug(m.method)
        paths.append(plot_top_view(m, result.map, out / f"{slug}_topview.png"))
        paths.append(plot_error_histogram(m, out / f"{slug}_terror.png"))
        if m.summary.rank_histogram:
            paths.append(plot_rank_histogram(m, out / f"{slug}_rank.png"))
    return paths


def _integer_y(ax: Any) -> None:
    from matplotlib.ticker import MaxNLocator

    ax.yaxis.set_major_locator(MaxNLocator(integer=True))


def _save(fig: Any, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path
