"""Matplotlib figures: joint trajectories, hand paths and stick-figure strips.

Every function returns a ``matplotlib.figure.Figure`` (Agg backend, no display needed);
callers save it or log it to TensorBoard.
"""
from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from . import dynamics  # noqa: E402
from .body import Body  # noqa: E402

COORD_LABELS = ["shoulder x", "shoulder y", "shoulder z", "elbow", "wrist x", "wrist y", "wrist z"]


def _np(x):
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def joint_positions(body: Body, q) -> np.ndarray:
    """Joint origins and tip (T×(L+1)×3) for coordinates q (T×nv)."""
    with torch.no_grad():
        return _np(dynamics.forward_kinematics(body, torch.as_tensor(q, dtype=torch.float64)))


def trajectories(t, paths: dict, title: str = "") -> plt.Figure:
    """Coordinates against time, one panel per coordinate; ``paths`` maps label → q (T×nv)."""
    t = _np(t)
    nv = next(iter(paths.values())).shape[-1]
    cols = min(nv, 4)
    rows = int(np.ceil(nv / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 2.4 * rows), squeeze=False)
    for k in range(rows * cols):
        ax = axes.flat[k]
        if k >= nv:
            ax.axis("off")
            continue
        for (label, q), style in zip(paths.items(), ["-", "--", ":", "-."]):
            ax.plot(t, _np(q)[:, k], style, label=label)
        ax.set_title(COORD_LABELS[k] if nv == 7 else f"q[{k}]", fontsize=9)
        ax.set_xlabel("t (s)", fontsize=8)
    axes.flat[0].set_ylabel("rad")
    axes.flat[0].legend(fontsize=7)
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def _equal_3d(ax, pts):
    lo, hi = pts.reshape(-1, 3).min(0), pts.reshape(-1, 3).max(0)
    c, r = (lo + hi) / 2, max((hi - lo).max() / 2, 0.05)
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    ax.set_zlabel("z")


def hand_paths(body: Body, paths: dict, title: str = "", ax=None) -> plt.Figure:
    """3-D hand-tip paths with the arm drawn at start and end; ``paths``: label → q (T×nv)."""
    fig = ax.figure if ax is not None else plt.figure(figsize=(5, 5))
    ax = ax or fig.add_subplot(projection="3d")
    allpts = []
    for (label, q), color in zip(paths.items(), ["C0", "C1", "C2", "C3"]):
        P = joint_positions(body, q)
        allpts.append(P)
        ax.plot(P[:, -1, 0], P[:, -1, 1], P[:, -1, 2], color=color, label=label)
        for k, alpha in ((0, 0.3), (-1, 1.0)):
            ax.plot(P[k, :, 0], P[k, :, 1], P[k, :, 2], "o-", color=color, alpha=alpha, ms=3)
    _equal_3d(ax, np.concatenate(allpts, 0))
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=7)
    return fig


def stick_strip(body: Body, paths: dict, frames: int = 6, title: str = "") -> plt.Figure:
    """Stick figures at ``frames`` evenly spaced instants, one panel each (views from +x)."""
    fig = plt.figure(figsize=(2.6 * frames, 3.0))
    Ps = {label: joint_positions(body, q) for label, q in paths.items()}
    allpts = np.concatenate(list(Ps.values()), 0)
    T = next(iter(Ps.values())).shape[0]
    for f, k in enumerate(np.linspace(0, T - 1, frames).round().astype(int)):
        ax = fig.add_subplot(1, frames, f + 1, projection="3d")
        for (label, P), color in zip(Ps.items(), ["C0", "C1", "C2", "C3"]):
            ax.plot(P[k, :, 0], P[k, :, 1], P[k, :, 2], "o-", color=color, ms=3, label=label)
            ax.plot(P[:k + 1, -1, 0], P[:k + 1, -1, 1], P[:k + 1, -1, 2], color=color, lw=0.5)
        _equal_3d(ax, allpts)
        ax.view_init(elev=15, azim=-30)
        ax.set_title(f"frame {k}", fontsize=8)
        ax.tick_params(labelsize=5)
    fig.axes[0].legend(fontsize=6)
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def motion_sheet(body: Body, t, paths: dict, title: str = "") -> plt.Figure:
    """One page per motion: joint trajectories (left) and the 3-D hand path (right)."""
    fig = plt.figure(figsize=(14, 5))
    gs = fig.add_gridspec(2, 6)
    t = _np(t)
    nv = next(iter(paths.values())).shape[-1]
    groups = [(0, 3, "shoulder"), (3, 4, "elbow"), (4, 7, "wrist")] if nv == 7 else [(0, nv, "q")]
    for g, (lo, hi, name) in enumerate(groups):
        ax = fig.add_subplot(gs[g // 2, (g % 2) * 2:(g % 2) * 2 + 2])
        for (label, q), style in zip(paths.items(), ["-", "--", ":", "-."]):
            qq = _np(q)
            for k in range(lo, hi):
                ax.plot(t, qq[:, k], style, color=f"C{k - lo}",
                        label=f"{label} {COORD_LABELS[k] if nv == 7 else k}")
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("t (s)", fontsize=8)
        ax.legend(fontsize=6, ncol=2)
    ax3 = fig.add_subplot(gs[:, 4:], projection="3d")
    hand_paths(body, paths, ax=ax3)
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def save(fig: plt.Figure, path) -> None:
    fig.savefig(path, dpi=110)
    plt.close(fig)
