"""Stick-figure contact sheets so a person can look at motion (matplotlib, headless)."""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .body.skeleton import PARENTS  # noqa: E402

_LEFT = {1, 4, 7, 10, 13, 16, 18, 20}


def _draw(ax, J: np.ndarray, color_l="tab:blue", color_r="tab:red", color_c="k", alpha=1.0):
    for j, p in enumerate(PARENTS):
        if p < 0:
            continue
        c = color_l if j in _LEFT else (color_r if j in {2, 5, 8, 11, 14, 17, 19, 21} else color_c)
        ax.plot([J[p, 0], J[j, 0]], [J[p, 1], J[j, 1]], color=c, lw=1.6, alpha=alpha)
    ax.scatter(J[:, 0], J[:, 1], s=4, c="k", alpha=alpha)


def contact_sheet(rows: list[np.ndarray], path: str | Path, titles: list[str] | None = None,
                  frames_per_row: int = 8, view: str = "side") -> None:
    """rows: list of joint arrays (T, 22, 3). Each row shows `frames_per_row` evenly spaced frames
    from the side (Z right, Y up) next to a top-down trajectory plot of the pelvis and feet."""
    n = len(rows)
    fig, axes = plt.subplots(n, frames_per_row + 1, figsize=(1.6 * (frames_per_row + 1), 2.4 * n), squeeze=False)
    for r, J in enumerate(rows):
        T = J.shape[0]
        idx = np.linspace(0, T - 1, frames_per_row).round().astype(int)
        for c, f in enumerate(idx):
            ax = axes[r, c]
            P = J[f]
            # side view: horizontal axis = direction of the pelvis travel, centred on the pelvis
            xy = np.stack((P[:, 2] - P[0, 2], P[:, 1]), 1) if view == "side" else np.stack((P[:, 0] - P[0, 0], P[:, 1]), 1)
            _draw(ax, np.concatenate((xy, P[:, :1]), 1))
            ax.axhline(0, color="0.6", lw=0.8)
            ax.set_xlim(-1.0, 1.0)
            ax.set_ylim(-0.1, 2.0)
            ax.set_aspect("equal")
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(f"{f / 30:.1f}s", fontsize=7)
        ax = axes[r, -1]
        ax.plot(J[:, 0, 0], J[:, 0, 2], "k-", lw=1)
        ax.plot(J[:, 10, 0], J[:, 10, 2], "b-", lw=0.6)
        ax.plot(J[:, 11, 0], J[:, 11, 2], "r-", lw=0.6)
        ax.plot(J[0, 0, 0], J[0, 0, 2], "go", ms=4)
        ax.set_aspect("equal", adjustable="datalim")
        ax.tick_params(labelsize=6)
        ax.set_title("top (x,z)", fontsize=7)
        if titles:
            axes[r, 0].set_ylabel(titles[r], fontsize=7)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def label_grid(clips: dict[str, list[np.ndarray]], path: str | Path, poses: int = 6, title: str = "") -> None:
    """One row per label, one column per clip (T, 22, 3) in the clip's first-frame canonical frame
    (facing +Z): a side-view strobe of `poses` evenly spaced poses, spread 0.6 m apart and moved by
    the body's own travel, so labels can be compared at a glance."""
    labels = list(clips)
    cols = max(len(v) for v in clips.values())
    fig, axes = plt.subplots(len(labels), cols, figsize=(2.6 * cols, 1.9 * len(labels)), squeeze=False)
    for r, label in enumerate(labels):
        for c in range(cols):
            ax = axes[r, c]
            ax.set_xticks([])
            ax.set_yticks([])
            if c >= len(clips[label]):
                ax.axis("off")
                continue
            J = clips[label][c]
            idx = np.linspace(0, len(J) - 1, poses).round().astype(int)
            for k, f in enumerate(idx):
                P = J[f]
                xy = np.stack((P[:, 2] - J[0, 0, 2] + 0.6 * k, P[:, 1]), 1)
                _draw(ax, np.concatenate((xy, P[:, :1]), 1), alpha=0.35 + 0.65 * k / max(1, poses - 1))
            ax.axhline(0, color="0.6", lw=0.8)
            # the floor-to-head band in every cell without fixing a limit: a fixed one conflicts
            # with the equal aspect (matplotlib then warns once per cell and ignores it)
            ax.update_datalim([(xy[0, 0], -0.1), (xy[0, 0], 2.0)])
            ax.autoscale_view()
            ax.set_aspect("equal", adjustable="datalim")
            if c == 0:
                ax.set_ylabel(label, fontsize=9)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)


def target_paths(paths: dict[str, np.ndarray], targets: list[tuple[float, float]], path: str | Path) -> None:
    """Top-down pelvis paths to reaching targets, one panel per method: paths[method] has shape
    (len(targets), n, T, 2) in each initial state's frame (x left, z forward; start at the origin)."""
    methods = list(paths)
    fig, axes = plt.subplots(1, len(methods), figsize=(3.6 * len(methods), 3.8), squeeze=False)
    colors = plt.cm.tab10(np.arange(len(targets)))
    for m, name in enumerate(methods):
        ax = axes[0, m]
        for k, (tx, tz) in enumerate(targets):
            for p in paths[name][k]:
                ax.plot(-p[:, 0], p[:, 1], color=colors[k], lw=0.6, alpha=0.5)  # x is the body's left: drawn leftwards
            ax.plot(-tx, tz, marker="*", ms=12, color=colors[k], mec="k")
        ax.plot(0, 0, "ko", ms=4)
        ax.set_aspect("equal")
        ax.set_xlim(-2.2, 2.2)
        ax.set_ylim(-2.2, 2.2)
        ax.grid(alpha=0.3)
        ax.set_title(name, fontsize=10)
        ax.set_xlabel("right (m)", fontsize=8)
        ax.set_ylabel("forward (m)", fontsize=8)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def stride_plot(series: dict[str, list[dict]], path: str | Path) -> None:
    """Stride length against leg length (eval persona --shape-png), one line per model, with the
    line through the origin that a stride in proportion to the leg would follow from the middle body."""
    fig, ax = plt.subplots(figsize=(5.2, 4.0))
    for name, rows in series.items():
        legs = np.array([r["leg_m"] for r in rows])
        st = np.array([r["stride_m"] for r in rows])
        ax.plot(legs, st, "o-", label=name)
        mid = len(rows) // 2
        if st[mid] > 0:
            ax.plot(legs, st[mid] * legs / legs[mid], ":", color=ax.lines[-1].get_color(), alpha=0.6)
    ax.set_xlabel("leg length, hip to ankle (m)")
    ax.set_ylabel("stride length (m)")
    ax.set_title("same description and goal (1.2 m/s), five bodies\n(dotted: in proportion to the leg)", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
