"""Matplotlib figures of bodies drawn link by link (:func:`link_segments`: branching trees,
closed loops and floating bases included): a mode shape's poses and a GIF of a creature
moving over the ground. Axes in m.
"""
from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np
import torch

from ..physics import dynamics
from ..physics.body import Body
from .figures import AXES, _equal_3d, _np


def link_segments(body: Body, q, base=None) -> np.ndarray:
    """Each link drawn as a segment from its joint to its far end (...×L×2×3, m): a
    cylinder's end (0, 0, −length) in its frame, for a general link twice its centre of
    mass (the far end of a uniform segment, e.g. a bone of :mod:`tflearn.mocap.skeleton`). Unlike
    :func:`~tflearn.plots.figures.joint_positions` this draws branching trees and closed loops correctly.
    ``base``: (R (3×3), p (3)), a rigid motion x ↦ R x + p of the whole body (a floating
    base's pose), or None."""
    with torch.no_grad():
        q = torch.as_tensor(q, dtype=torch.float64)
        Rw, x = dynamics.forward_kinematics_rot(body, dynamics.joint_rotations(body, q), q)
        segs = []
        for i, link in enumerate(body.links):
            end = ((0.0, 0.0, -link.length) if np.isfinite(link.length)
                   else tuple(2 * c for c in link.com))
            tip = x[..., i, :] + (Rw[i] @ torch.as_tensor(end, dtype=q.dtype).unsqueeze(-1)).squeeze(-1)
            segs.append(torch.stack([x[..., i, :], tip], dim=-2))
        out = _np(torch.stack(segs, dim=-3))
    if base is not None:
        R, p = (np.asarray(a, dtype=float) for a in base)
        out = out @ R.T + p
    return out


def mode_shape(body: Body, poses: dict, title: str = "") -> plt.Figure:
    """A mode shape as stick figures: ``poses`` label → (q (nv), base) with base as in
    :func:`link_segments`, e.g. {"rest": …, "−α": …, "+α": …}, overlaid in one 3-D panel
    (the first dashed grey, the rest in colours) and, in a second, seen along the axis in
    which the first pose is thinnest (the plane of its two widest axes); axes in m."""
    fig = plt.figure(figsize=(10, 4.6))
    ax3 = fig.add_subplot(1, 2, 1, projection="3d")
    ax2 = fig.add_subplot(1, 2, 2)
    segs = {label: link_segments(body, q, base) for label, (q, base) in poses.items()}
    styles = [dict(color="0.55", ls="--", lw=1.2)] + [dict(color=f"C{k}", lw=2.0)
                                                      for k in range(len(poses))]
    first = next(iter(segs.values())).reshape(-1, 3)
    h, v = sorted(np.argsort(first.max(0) - first.min(0))[1:])
    for (label, S), style in zip(segs.items(), styles):
        for k, seg in enumerate(S):
            kw = dict(style, label=label if k == 0 else None)
            ax3.plot(seg[:, 0], seg[:, 1], seg[:, 2], marker="o", ms=2.5, **kw)
            ax2.plot(seg[:, h], seg[:, v], marker="o", ms=2.5, **kw)
    pts = np.concatenate([S.reshape(-1, 3) for S in segs.values()])
    _equal_3d(ax3, pts, fontsize=8)
    ax3.view_init(elev=15, azim=-60)
    ax2.set_aspect("equal", adjustable="datalim")
    ax2.set_xlabel(f"{AXES[h]} (m)")
    ax2.set_ylabel(f"{AXES[v]} (m)")
    ax2.grid(True, lw=0.3)
    ax2.legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def side_view_gif(body: Body, t, q, path, fps: int = 25, title: str = "", com=None) -> int:
    """A GIF of a body moving over the ground z = 0, seen from −y (x–z plane, m): its links
    as segments (:func:`link_segments`; free joints included), the centre of mass's path
    (``com``, T×3) as a trail, frame k at the sample nearest t = k/fps. Written
    atomically; returns the number of frames."""
    from matplotlib.animation import PillowWriter

    from ..io.files import replacing
    t = np.asarray(t)
    segs = link_segments(body, q)                                   # T×L×2×3
    picks = np.unique(np.searchsorted(t, np.arange(t[0], t[-1] + 1e-9, 1.0 / fps)).clip(0, t.size - 1))
    pts = segs.reshape(-1, 3)
    fig, ax = plt.subplots(figsize=(8, 3.2), dpi=100)
    pad = 0.05
    ax.set_xlim(pts[:, 0].min() - pad, pts[:, 0].max() + pad)
    ax.set_ylim(-0.02, max(pts[:, 2].max(), 0.1) + pad)
    ax.set_aspect("equal")
    ax.axhline(0.0, color="0.4", lw=1.0)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("z (m)")
    lines = [ax.plot([], [], "o-", color="C0", ms=2.5, lw=2.0)[0] for _ in range(segs.shape[1])]
    trail, = ax.plot([], [], color="C1", lw=1.0, label="centre of mass")
    if com is not None:
        ax.legend(fontsize=8, loc="upper right")
    label = ax.set_title(title)
    fig.tight_layout()
    with replacing(path) as tmp:
        writer = PillowWriter(fps=fps)
        with writer.saving(fig, str(tmp), dpi=100):
            for k in picks:
                for line, seg in zip(lines, segs[k]):
                    line.set_data(seg[:, 0], seg[:, 2])
                if com is not None:
                    trail.set_data(com[:k + 1, 0], com[:k + 1, 2])
                label.set_text(f"{title}  t = {t[k]:.2f} s")
                writer.grab_frame()
    plt.close(fig)
    return int(picks.size)
