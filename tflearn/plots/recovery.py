"""Matplotlib figures of pushes and recovery (``tflearn perturb``): each controller's hand
deviation over time and its hand paths, and the largest deviation against the push's
impulse. Distances in cm, positions in m.
"""
from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.lines import Line2D

from ..physics.body import Body
from .figures import _equal_3d, _np, joint_positions


def push_response(body: Body, t, base: dict, pushed: dict, window, tol: float = 0.01,
                  title: str = "") -> plt.Figure:
    """How each controller responds to a push: left, the hand's distance from its own
    unperturbed path (cm) against time (s), the push window shaded and the recovery
    band ``tol`` dotted; right, the 3-D hand paths (m), unperturbed thin dashed and pushed
    solid, the part under the push in red. ``base``, ``pushed``: controller → q (T×nv)."""
    t = _np(t)
    fig = plt.figure(figsize=(13, 5.2))
    ax = fig.add_subplot(1, 2, 1)
    ax3 = fig.add_subplot(1, 2, 2, projection="3d")
    inside = (t >= window[0]) & (t <= window[1]) if window else np.zeros_like(t, dtype=bool)
    allpts = []
    for n, (label, q) in enumerate(pushed.items()):
        P0, P1 = joint_positions(body, base[label]), joint_positions(body, q)
        allpts += [P0, P1]
        ax.plot(t, 100 * np.linalg.norm(P1[:, -1] - P0[:, -1], axis=-1), color=f"C{n}", lw=1.6,
                label=label)
        ax3.plot(*P0[:, -1].T, "--", color=f"C{n}", lw=0.9)
        ax3.plot(*P1[:, -1].T, color=f"C{n}", lw=1.6, label=f"{label} (pushed)")
        ax3.plot(*P1[inside, -1].T, color="red", lw=3)
    if window:
        ax.axvspan(window[0], window[1], color="red", alpha=0.15, label="push")
    ax.axhline(100 * tol, color="0.3", ls=":", lw=1, label=f"{100 * tol:g} cm")
    ax.set_yscale("symlog", linthresh=0.1)
    ax.set_ylim(bottom=0)
    ax.set_xlabel("t (s)")
    ax.set_ylabel("hand distance from unperturbed path (cm)")
    ax.grid(True, lw=0.3)
    ax.legend(fontsize=8)
    _equal_3d(ax3, np.concatenate(allpts, 0))
    handles, labels = ax3.get_legend_handles_labels()
    handles += [Line2D([], [], color="0.3", ls="--", lw=0.9), Line2D([], [], color="red", lw=3)]
    labels += ["unperturbed", "under the push"]
    ax3.legend(handles, labels, fontsize=7, loc="upper left")
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def deviation_sweep(rows: dict, title: str = "") -> plt.Figure:
    """Largest hand deviation (cm) against push impulse (N·s), one colour per controller,
    one marker per push direction; ``rows``: controller → [{"impulse", "impulse_Ns",
    "max_hand_dev"}, ...]."""
    fig, ax = plt.subplots(figsize=(9, 4.6))
    markers = "osd^v<>"
    dirs = []
    for n, (label, rs) in enumerate(rows.items()):
        by_dir = {}
        for r in rs:
            d = tuple(float(x) for x in np.round(np.asarray(r["impulse"]) / max(r["impulse_Ns"], 1e-300), 3))
            by_dir.setdefault(d, []).append((r["impulse_Ns"], 100 * r["max_hand_dev"]))
        for m, (d, pts) in enumerate(sorted(by_dir.items())):
            if d not in dirs:
                dirs.append(d)
            x, y = np.asarray(sorted(pts)).T
            ax.plot(x, y, marker=markers[dirs.index(d) % len(markers)], color=f"C{n}", lw=1.2,
                    ms=5, label=label if m == 0 else None)
    handles, labels = ax.get_legend_handles_labels()
    for k, d in enumerate(dirs):
        handles.append(Line2D([], [], color="0.4", marker=markers[k % len(markers)], lw=0))
        labels.append(f"direction {d}")
    ax.legend(handles, labels, fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax.set_xlabel("push impulse (N·s)")
    ax.set_ylabel("largest hand deviation (cm)")
    ax.set_yscale("log")
    ax.grid(True, lw=0.3, which="both")
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    return fig
