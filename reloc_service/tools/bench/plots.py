"""Plots of a ``reloc bench`` result (matplotlib, imported only here): latency vs map size,
throughput vs concurrent clients, and the per-stage latency of each method. Small PNGs meant
to be committed next to ``docs/performance.md``."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

#: Stages in the order they run, as plotted and tabulated (raw stage names summed into each).
STAGE_GROUPS: dict[str, tuple[str, ...]] = {
    "decode": ("decode",), "features": ("features",), "place": ("place",),
    "match": ("match", "classify"), "solve": ("solve", "align"), "verify": ("verify",)}


def stage_groups_ms(stages_ms: Mapping[str, float], wall_ms: float) -> dict[str, float]:
    """Milliseconds per :data:`STAGE_GROUPS` entry, plus ``other`` (the wall time not in any
    stage: frame creation, locks, bookkeeping; never negative)."""
    out = {g: sum(stages_ms.get(s, 0.0) for s in names) for g, names in STAGE_GROUPS.items()}
    out["other"] = max(0.0, wall_ms - sum(out.values()))
    return out


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_all(result: Mapping[str, Any], directory: str | Path) -> list[Path]:
    """Every plot the sections of ``result`` allow, written into ``directory``."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    written = []
    if any("error" not in r for r in result.get("scaling", {}).get("sizes", [])):
        written.append(plot_scaling(result["scaling"], directory / "bench_map_size.png"))
    if result.get("throughput", {}).get("runs"):
        written.append(plot_throughput(result["throughput"],
                                       directory / "bench_throughput.png"))
    if result.get("latency", {}).get("methods"):
        written.append(plot_stages(result["latency"], directory / "bench_stages.png"))
    return written


def plot_scaling(scaling: Mapping[str, Any], path: Path) -> Path:
    """Median latency of each method (and the place finders alone) against keyframes."""
    plt = _pyplot()
    rows = [r for r in scaling["sizes"] if "error" not in r]
    sizes = [r["keyframes"] for r in rows]
    fig, (ax, ax_mem) = plt.subplots(1, 2, figsize=(9, 3.6))
    for method in scaling["methods"]:
        ax.plot(sizes, [r["methods"][method]["p50_ms"] for r in rows], "o-", label=method)
    for name in sorted({k for r in rows for k in r.get("place_finder_ms", {})}):
        ax.plot(sizes, [r["place_finder_ms"].get(name) for r in rows], "x--",
                label=f"{name} place finder alone")
    plain = [r.get("plain_opencv", {}).get("p50_ms") for r in rows]
    if any(p is not None for p in plain):
        ax.plot(sizes, plain, "s:", color="grey", label="plain OpenCV")
    ax.set(xscale="log", yscale="log", xlabel="keyframes in the map", ylabel="p50 latency (ms)",
           title="latency vs map size")
    _size_ticks(ax, sizes)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    ax_mem.plot(sizes, [r.get("map_rss_mb") for r in rows], "o-", label="resident memory (MB)")
    ax_mem.plot(sizes, [r.get("snapshot_mb") for r in rows], "s--", label="snapshot on disk (MB)")
    ax_mem.set(xscale="log", yscale="log", xlabel="keyframes in the map", ylabel="MB",
               title="memory of the map")
    _size_ticks(ax_mem, sizes)
    ax_mem.grid(True, which="both", alpha=0.3)
    ax_mem.legend(fontsize=7)
    return _save(fig, path)


def plot_throughput(throughput: Mapping[str, Any], path: Path) -> Path:
    """Queries per second and p99 latency against concurrent clients."""
    plt = _pyplot()
    modes = throughput.get("modes") or {throughput.get("mode", "thread"): throughput["runs"]}
    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    ax2 = ax.twinx()
    for k, (mode, runs) in enumerate(modes.items()):
        clients = [r["clients"] for r in runs]
        ax.plot(clients, [r["queries_per_s"] for r in runs], "o-", color=f"C{k}",
                label=f"{mode} workers: queries/s")
        ax2.plot(clients, [r["p99_ms"] for r in runs], "s--", color=f"C{k}", alpha=0.6,
                 label=f"{mode} workers: p99")
        ax.set_xticks(clients, [str(c) for c in clients])
    ax.set(xscale="log", xlabel="concurrent clients", ylabel="answered queries / s (solid)",
           title=f"throughput, {throughput['method']}, {throughput['workers']} workers")
    ax.set_ylim(bottom=0)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7, loc="upper left")
    ax2.set_ylabel("p99 round trip, ms (dashed)")
    ax2.set_ylim(bottom=0)
    return _save(fig, path)


def plot_stages(latency: Mapping[str, Any], path: Path) -> Path:
    """Stacked median stage times of each method (in-process), with the decode + features
    limit of the same queries as a line."""
    plt = _pyplot()
    methods = latency["methods"]
    labels = list(methods)
    groups = [stage_groups_ms(m["stages_ms"], m["p50_ms"]) for m in methods.values()]
    fig, ax = plt.subplots(figsize=(6.5, 3.6))
    bottom = [0.0] * len(labels)
    for name in [*STAGE_GROUPS, "other"]:
        values = [g[name] for g in groups]
        ax.bar(labels, values, bottom=bottom, label=name)
        bottom = [b + v for b, v in zip(bottom, values, strict=True)]
    limit = latency["limit"]["sift_limit_p50_ms"]
    ax.axhline(limit, color="black", linestyle="--", linewidth=1,
               label=f"decode + SIFT alone ({limit:.0f} ms)")
    orb = latency["limit"]["orb_limit_p50_ms"]
    ax.axhline(orb, color="grey", linestyle=":", linewidth=1,
               label=f"decode + ORB alone ({orb:.0f} ms)")
    ax.set(ylabel="median ms per query", title="where the time goes (in-process)")
    ax.tick_params(axis="x", labelsize=8)
    ax.legend(fontsize=7, ncol=2)
    return _save(fig, path)


def _size_ticks(ax: Any, sizes: list[int]) -> None:
    """Label the map sizes themselves on a log axis (not powers of ten)."""
    from matplotlib.ticker import NullFormatter

    ax.set_xticks(sizes, [str(s) for s in sizes])
    ax.xaxis.set_minor_formatter(NullFormatter())


def _save(fig: Any, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    import matplotlib.pyplot as plt

    plt.close(fig)
    return path
