"""Draw docs/img/overview.png, the README's first picture: who sends what to the service and
what comes back. Run: python scripts/draw_overview.py (needs matplotlib, the [tools] extra)."""

from __future__ import annotations

import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.patches import FancyArrowPatch, FancyBboxPatch  # noqa: E402

CLIENTS = [
    ("drone 1: VIO lost track", "reloc-client / RelocClient"),
    ("drone 2: same map", "RelocClient"),
    ("ROS 2 node", "rmw_zenoh: PoseWithCovarianceStamped, TF"),
    ("ground station", "maps: keyframes in, train, copy"),
]


def box(ax, x: float, y: float, w: float, h: float, title: str, sub: str, color: str) -> None:
    ax.add_patch(FancyBboxPatch((x, y), w, h, boxstyle="round,pad=0.02", fc=color, ec="#333333"))
    ax.text(x + w / 2, y + h * 0.62, title, ha="center", va="center", fontsize=10, weight="bold")
    ax.text(x + w / 2, y + h * 0.28, sub, ha="center", va="center", fontsize=8)


def arrow(ax, start: tuple[float, float], end: tuple[float, float], text: str, dy: float) -> None:
    ax.add_patch(FancyArrowPatch(start, end, arrowstyle="-|>", mutation_scale=12, color="#555555"))
    ax.text((start[0] + end[0]) / 2, (start[1] + end[1]) / 2 + dy, text, ha="center",
            fontsize=7.5, color="#333333")


def main(out: Path) -> None:
    fig, ax = plt.subplots(figsize=(11, 4.2))
    ax.set_xlim(0, 11)
    ax.set_ylim(0, 4.2)
    ax.axis("off")
    for i, (title, sub) in enumerate(CLIENTS):
        box(ax, 0.1, 3.2 - i * 1.0, 2.9, 0.75, title, sub, "#e8f1fb")
    box(ax, 3.9, 1.4, 1.7, 1.4, "Zenoh", "peers, routers,\nACL, TLS", "#f4f4f4")
    box(ax, 7.3, 0.7, 3.6, 2.8, "", "", "#eaf6e6")
    ax.text(9.1, 3.2, "reloc serve", ha="center", fontsize=11, weight="bold")
    for i, line in enumerate(["keyframe maps + trained models (journaled)",
                              "place finder -> pose finder (P3P)",
                              "verification: chance, spread, uniqueness,",
                              "the query's intrinsics; covariance",
                              "worker processes, replicas"]):
        ax.text(9.1, 2.7 - i * 0.42, line, ha="center", fontsize=8)
    for i in range(len(CLIENTS)):
        y = 3.57 - i * 1.0
        arrow(ax, (3.05, y), (3.9, 2.1 + 0.1 * (1.5 - i)), "", 0)
    arrow(ax, (5.65, 2.4), (7.3, 2.4), "keyframes, relocalize(image)", 0.1)
    arrow(ax, (7.3, 1.8), (5.65, 1.8), "world_from_cam + covariance", 0.1)
    ax.text(6.47, 1.5, "or 'not relocalized: why'", ha="center", fontsize=7.5, color="#333333")
    ax.set_title("reloc: one relocalizer that drones, ground stations and ROS 2 share over Zenoh",
                 fontsize=11)
    fig.tight_layout()
    fig.savefig(out, dpi=100)


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path("docs/img/overview.png"))
