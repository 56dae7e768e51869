"""Matplotlib figures of motions — joint trajectories, errors, hand paths, stick-figure strips —
and what every figure of :mod:`tflearn.plots` shares (joint positions, line styles, axes, saving).

Every function returns a ``matplotlib.figure.Figure`` (Agg backend, no display needed);
callers save it (:func:`save`) or log it to TensorBoard. The other families:
:mod:`tflearn.plots.model` (fields, hand forces, profiles, weights, learning curves),
:mod:`tflearn.plots.bodies` (bodies as link segments: mode shapes, a creature's side view) and
:mod:`tflearn.plots.recovery` (pushes and recovery).

Conventions of the motion figures (:func:`trajectories`, :func:`joint_errors`,
:func:`hand_paths`, :func:`motion_sheet`, :func:`stick_strip`): ``paths`` maps a label to
coordinates q (T×nv) and its first entry is the reference (the target). With more than
one path the reference is drawn last and on top, thin and dashed, over the thicker solid
simulated lines, so that it stays visible where they coincide. Every axis carries its
unit: time in s, joint coordinates in rad (named by :func:`coordinate_names`, e.g.
"shoulder rotation vector x", "elbow angle"), positions in m. A joint axis spans at least
:data:`MIN_SPAN` rad, so that a coordinate that barely moves does not magnify numerical
noise into what looks like an error.
"""
from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import torch
from matplotlib.lines import Line2D

from ..physics import dynamics
from ..physics.body import JOINT_NAMES, Body

#: The smallest span (rad) of a joint coordinate's y axis.
MIN_SPAN = 0.1
AXES = "xyz"


def _np(x):
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def joint_positions(body: Body, q) -> np.ndarray:
    """Joint origins and tip (T×(L+1)×3) for coordinates q (T×nv)."""
    with torch.no_grad():
        return _np(dynamics.forward_kinematics(body, torch.as_tensor(q, dtype=torch.float64)))


def joint_groups(body: Body | None, nv: int | None = None) -> list:
    """The body's moving joints in coordinate order: [(joint name, kind, [(index,
    component name)])], kind "ball" or "hinge". A ball joint's components are its rotation
    vector's x, y and z ("shoulder rotation vector x"), a hinge's its angle ("elbow
    angle"); joints are named by :data:`JOINT_NAMES`, else by their link. Without a body,
    the thesis' arm when nv = 7, else one group "coordinates" of q[0] … q[nv−1]."""
    if body is None:
        if nv == 7:
            from ..physics.body import arm
            body = arm()
        else:
            return [("coordinates", "other", [(k, f"q[{k}]") for k in range(nv)])]
    groups = []
    for i, link in enumerate(body.links):
        if not link.dof:
            continue
        name, s = JOINT_NAMES.get(link.name, link.name), body.slice(i)
        if link.joint == "ball":
            comps = [(k, f"{name} rotation vector {AXES[c]}") for c, k in enumerate(range(s.start, s.stop))]
        else:
            comps = [(s.start, f"{name} angle")]
        groups.append((name, link.joint, comps))
    return groups


def coordinate_names(body: Body | None, nv: int | None = None) -> list:
    """One name per coordinate of ν (see :func:`joint_groups`), without the unit (rad)."""
    return [c for _, _, comps in joint_groups(body, nv) for _, c in comps]


def _styles(paths: dict) -> list:
    """Line keywords per path: the reference (first) thin, dashed and on top when there
    are others; the others thick and solid (then dash-dot, dotted) beneath it."""
    n = len(paths)
    if n == 1:
        return [dict(ls="-", lw=1.6, zorder=3)]
    rest = [dict(ls=ls, lw=3.0, alpha=0.7, zorder=2) for ls in ["-", "-.", ":", "-"]]
    return [dict(ls="--", lw=1.3, zorder=4)] + [rest[i % len(rest)] for i in range(n - 1)]


def _set_span(ax, values, ref=None, min_span: float = MIN_SPAN, centre=None) -> None:
    """y limits over the finite ``values`` spanning at least ``min_span`` and the range of
    ``ref`` (default: the values' own range), centred on the values (or ``centre``)."""
    v = np.concatenate([np.asarray(x, dtype=float).ravel() for x in values]) \
        if isinstance(values, (list, tuple)) else np.asarray(values, dtype=float).ravel()
    v = v[np.isfinite(v)]
    if not v.size:
        return
    lo, hi = v.min(), v.max()
    r = np.asarray(ref if ref is not None else v, dtype=float).ravel()
    r = r[np.isfinite(r)]
    span = max(hi - lo, float(r.max() - r.min()) if r.size else 0.0, min_span)
    c = (lo + hi) / 2 if centre is None else centre
    half = max(span / 2, hi - c, c - lo) * 1.08
    ax.set_ylim(c - half, c + half)


def _rows(groups) -> list:
    """The rows of :func:`_joint_axes`: a joint's components per row, or one coordinate a
    row when there is no body to group them by."""
    if any(kind == "other" for _, kind, _ in groups):
        return [[c] for _, _, comps in groups for c in comps]
    return [comps for _, _, comps in groups]


def _n_rows(groups) -> int:
    return len(_rows(groups))


def _joint_axes(fig, groups):
    """One axis per coordinate, a row per joint: a ball joint's three components side by
    side, a hinge across the whole row, so no cell is empty. Returns [(axis, index, name)]."""
    rows = _rows(groups)
    cols = max(len(r) for r in rows)
    gs = fig.add_gridspec(len(rows), cols)
    out = []
    for r, comps in enumerate(rows):
        edges = np.linspace(0, cols, len(comps) + 1).round().astype(int)
        for (k, name), lo, hi in zip(comps, edges[:-1], edges[1:]):
            out.append((fig.add_subplot(gs[r, lo:hi]), k, name))
    return out


def trajectories(t, paths: dict, title: str = "", body: Body | None = None) -> plt.Figure:
    """Coordinates against time, one panel per coordinate and a row per joint; ``paths``
    maps label → q (T×nv), the first the reference (see the module). Axes: t (s) and the
    coordinate's name (rad) from ``body`` (default: the arm when nv = 7)."""
    t = _np(t)
    qs = {label: _np(q) for label, q in paths.items()}
    ref = next(iter(qs.values()))
    groups = joint_groups(body, ref.shape[-1])
    fig = plt.figure(figsize=(13, 2.7 * _n_rows(groups) + 0.6))
    styles = _styles(qs)
    for ax, k, name in _joint_axes(fig, groups):
        for n, ((label, q), style) in enumerate(zip(qs.items(), styles)):
            ax.plot(t, q[:, k], color=f"C{n}", label=label, **style)
        _set_span(ax, [q[:, k] for q in qs.values()], ref[:, k])
        ax.set_xlabel("t (s)", fontsize=9)
        ax.set_ylabel(f"{name} (rad)", fontsize=9)
        ax.tick_params(labelsize=8)
        ax.grid(True, lw=0.3)
    fig.axes[0].legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def joint_errors(body: Body, t, paths: dict, title: str = "") -> plt.Figure:
    """Per-coordinate error of each path against the first (the reference) over time:
    e = q ⊖ q_ref (:func:`tflearn.physics.configspace.difference`: the rotation from reference to
    path per ball joint, child frame; the angle difference per hinge), in rad, one panel
    per coordinate as :func:`trajectories`. Each y axis is centred on 0 and spans at least
    the reference's own range in that coordinate and :data:`MIN_SPAN`, so an error reads
    against the size of the motion."""
    from ..physics.configspace import difference
    t = _np(t)
    qs = {label: torch.as_tensor(q, dtype=torch.float64) for label, q in paths.items()}
    labels = list(qs)
    ref = qs[labels[0]]
    with torch.no_grad():
        errs = {label: _np(difference(body, ref, qs[label])) for label in labels[1:]}
    groups = joint_groups(body)
    fig = plt.figure(figsize=(13, 2.7 * _n_rows(groups) + 0.6))
    r = _np(ref)
    for ax, k, name in _joint_axes(fig, groups):
        ax.axhline(0.0, color="0.6", lw=0.8)
        for n, (label, e) in enumerate(errs.items()):
            ax.plot(t, e[:, k], color=f"C{n + 1}", lw=1.6, label=f"{label} − {labels[0]}")
        _set_span(ax, [e[:, k] for e in errs.values()] + [0.0], r[:, k], centre=0.0)
        ax.set_xlabel("t (s)", fontsize=9)
        ax.set_ylabel(f"{name} error (rad)", fontsize=9)
        ax.tick_params(labelsize=8)
        ax.grid(True, lw=0.3)
    if errs:
        fig.axes[0].legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def _equal_3d(ax, pts, fontsize: float = 9):
    pts = pts.reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(-1)]           # a failed simulation's path is NaN
    lo, hi = pts.min(0), pts.max(0)
    c, r = (lo + hi) / 2, max((hi - lo).max() / 2, 0.05)
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)
    ax.set_xlabel("x (m)", fontsize=fontsize)
    ax.set_ylabel("y (m)", fontsize=fontsize)
    ax.set_zlabel("z (m)", fontsize=fontsize)


def hand_paths(body: Body, paths: dict, title: str = "", ax=None) -> plt.Figure:
    """3-D hand-tip paths with the arm drawn at start (faint) and end; ``paths``: label →
    q (T×nv), the first the reference, drawn dashed on top of the others (see the
    module). Axes x, y, z in m."""
    fig = ax.figure if ax is not None else plt.figure(figsize=(6, 6))
    ax = ax or fig.add_subplot(projection="3d")
    ax.computed_zorder = False                   # draw by zorder: the reference on top
    allpts = []
    for (label, q), color, style in zip(paths.items(), ["C0", "C1", "C2", "C3"], _styles(paths)):
        P = joint_positions(body, q)
        allpts.append(P)
        for k, alpha in ((0, 0.3), (-1, 1.0)):
            ax.plot(P[k, :, 0], P[k, :, 1], P[k, :, 2], "o-", color=color, alpha=alpha, ms=3,
                    lw=1.2, zorder=style["zorder"] - 0.5)
        ax.plot(P[:, -1, 0], P[:, -1, 1], P[:, -1, 2], color=color, label=f"{label} hand path",
                **style)
    _equal_3d(ax, np.concatenate(allpts, 0))
    ax.set_title(title, fontsize=10)
    handles, labels = ax.get_legend_handles_labels()
    handles.append(Line2D([], [], color="0.4", marker="o", ms=3, lw=1.2))
    labels.append("arm at start (faint) and end")
    ax.legend(handles, labels, fontsize=8, loc="upper left")
    return fig


def stick_strip(body: Body, paths: dict, frames: int = 6, title: str = "") -> plt.Figure:
    """Stick figures at ``frames`` evenly spaced instants, one panel each (views from +x);
    axes in m."""
    fig = plt.figure(figsize=(2.8 * frames, 3.3))
    Ps = {label: joint_positions(body, q) for label, q in paths.items()}
    allpts = np.concatenate(list(Ps.values()), 0)
    T = next(iter(Ps.values())).shape[0]
    for f, k in enumerate(np.linspace(0, T - 1, frames).round().astype(int)):
        ax = fig.add_subplot(1, frames, f + 1, projection="3d")
        ax.computed_zorder = False               # the reference's arm on top
        for (label, P), color, style in zip(Ps.items(), ["C0", "C1", "C2", "C3"], _styles(Ps)):
            ax.plot(P[k, :, 0], P[k, :, 1], P[k, :, 2], "o-", color=color, ms=3, label=label,
                    lw=min(style["lw"], 2.2), alpha=style.get("alpha", 1.0), zorder=style["zorder"])
            ax.plot(P[:k + 1, -1, 0], P[:k + 1, -1, 1], P[:k + 1, -1, 2], color=color, lw=0.5,
                    zorder=style["zorder"])
        _equal_3d(ax, allpts, fontsize=7)
        ax.set_box_aspect(None, zoom=0.85)       # room for the z label
        ax.view_init(elev=15, azim=-30)
        ax.set_title(f"frame {k}", fontsize=8)
        ax.tick_params(labelsize=6)
    fig.axes[0].legend(fontsize=6)
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def motion_sheet(body: Body, t, paths: dict, title: str = "") -> plt.Figure:
    """One page per motion: a panel per joint (left; its components in colours, the paths
    in line styles, the reference dashed on top) and the 3-D hand path (right)."""
    t = _np(t)
    qs = {label: _np(q) for label, q in paths.items()}
    ref = next(iter(qs.values()))
    groups = joint_groups(body)
    rows = len(groups)
    height = max(6.0, 2.4 * rows + 0.8)
    fig = plt.figure(figsize=(15, height))
    # a fixed layout (margins in inches): tight_layout cost three times the drawing
    gs = fig.add_gridspec(rows, 2, width_ratios=[1.35, 1], left=0.05, right=0.99, wspace=0.08,
                          bottom=0.55 / height, top=1 - 0.45 / height, hspace=0.35)
    styles = _styles(qs)
    for g, (joint, _kind, comps) in enumerate(groups):
        ax = fig.add_subplot(gs[g, 0])
        idx = [k for k, _ in comps]
        for q, style in zip(qs.values(), styles):
            for c, k in enumerate(idx):
                ax.plot(t, q[:, k], color=f"C{c}", **style)
        _set_span(ax, [q[:, idx] for q in qs.values()], ref[:, idx])
        quantity = comps[0][1] if len(comps) == 1 else f"{joint} rotation vector"
        ax.set_ylabel(f"{quantity} (rad)", fontsize=9)
        ax.set_xlabel("t (s)", fontsize=9)
        ax.tick_params(labelsize=8)
        ax.grid(True, lw=0.3)
        handles, labels = [], []
        if len(comps) > 1:
            handles += [Line2D([], [], color=f"C{c}", lw=2) for c in range(len(comps))]
            labels += [name.rsplit(" ", 1)[-1] for _, name in comps]
        if len(qs) > 1 or len(comps) == 1:
            handles += [Line2D([], [], color="0.25", **{k: v for k, v in s.items() if k != "zorder"})
                        for s in styles]
            labels += list(qs)
        ax.legend(handles, labels, fontsize=8, ncol=len(handles), loc="best")
    ax3 = fig.add_subplot(gs[:, 1], projection="3d")
    hand_paths(body, paths, ax=ax3)
    fig.suptitle(title)
    return fig


def save(fig: plt.Figure, path) -> None:
    """Write a figure (format from the file's suffix) atomically and close it."""
    from ..io.files import replacing
    path = Path(path)
    with replacing(path) as tmp:
        fig.savefig(tmp, dpi=110, format=path.suffix.lstrip(".") or "png")
    plt.close(fig)
