"""Matplotlib figures: joint trajectories, hand paths and stick-figure strips.

Every function returns a ``matplotlib.figure.Figure`` (Agg backend, no display needed);
callers save it or log it to TensorBoard.

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

import matplotlib

matplotlib.use("Agg")
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


# ------------------------------------------------------------------ fields and weights

def hand_jacobian(body: Body, q) -> torch.Tensor:
    """The hand-tip Jacobian J (...×3×nv) in the body's velocity coordinates: ṗ = J v.

    Velocities v are the joints' child-frame angular velocities (ball) and angle rates
    (hinge), the duals of the torques, so J is the geometric Jacobian, not ∂p/∂ν: a
    child-frame angular velocity ω of joint i turns everything beyond it about the
    joint's origin x_i, so its columns are (R_i e_k) × (p − x_i) for a ball joint
    (k = 1, 2, 3) and (R_i a) × (p − x_i) for a hinge with axis a, R_i the link's world
    rotation and p the tip. q (...×nv)."""
    q = torch.as_tensor(q, dtype=torch.float64)
    Rw, x = dynamics.forward_kinematics_rot(body, dynamics.joint_rotations(body, q), q)
    cols = []
    for i, link in enumerate(body.links):
        if link.joint == "ball":
            W = Rw[i]
        elif link.joint == "hinge":
            W = Rw[i] @ torch.as_tensor(link.axis, dtype=q.dtype)[:, None]
        else:
            continue
        r = (x[..., -1, :] - x[..., i, :]).unsqueeze(-1)
        cols.append(torch.linalg.cross(W, r.expand_as(W), dim=-2))
    return torch.cat(cols, dim=-1)


def hand_force(body: Body, q, tau) -> torch.Tensor:
    """The hand force F (...×3) whose joint torques Jᵀ F best match τ: F = (Jᵀ)⁺ τ.

    J (3×nv) is :func:`hand_jacobian` at q (...×nv) and τ (...×nv) is dual to the
    velocities (power τ·v = F·ṗ). F minimises ‖Jᵀ F − τ‖ (the minimum-norm minimiser
    where J loses rank); where J has full row rank F = (J Jᵀ)⁻¹ J τ, and Jᵀ F = τ exactly
    whenever τ is a torque some hand force produces (τ in the range of Jᵀ)."""
    Jt = hand_jacobian(body, q).transpose(-1, -2)
    tau = torch.as_tensor(tau, dtype=Jt.dtype)
    return (torch.linalg.pinv(Jt) @ tau.unsqueeze(-1)).squeeze(-1)


def field_slice(body: Body, eta, K, dims=(0, 3), q_ref=None, span=None, n: int = 21) -> dict:
    """One field χ(ν) = −K(ν−η)·exp(−½(ν−η)ᵀK(ν−η)) on a 2-D slice of joint space.

    The slice goes through q_ref (default η) along coordinates ``dims`` = (i, j), over
    q_ref ± ``span`` rad in each (default 1.8/√λ_min of the 2×2 block K[dims, dims],
    at most 1.5 rad: the field's magnitude peaks 1/√λ from η along an eigenvector), on an
    n×n grid. Returns numpy arrays: "x" (n) and "y" (n) the values of ν_i and ν_j;
    "q" (n×n×nv) the postures, row r and column c at (x[c], y[r]); "chi" (n×n×nv) the
    field torques; "p" (n×n×3) hand-tip positions; "F" (n×n×3) the hand forces
    :func:`hand_force` of the torques. eta (nv), K (nv×nv) positive definite."""
    from ..model.fields import FieldBasis, as_float
    eta, K = as_float(eta), as_float(K)
    q_ref = eta if q_ref is None else as_float(q_ref)
    i, j = dims
    if span is None:
        lam = float(torch.linalg.eigvalsh(K[[i, j]][:, [i, j]])[0])
        span = min(1.8 / lam ** 0.5, 1.5)
    x = q_ref[i] + torch.linspace(-span, span, n, dtype=torch.float64)
    y = q_ref[j] + torch.linspace(-span, span, n, dtype=torch.float64)
    q = q_ref.expand(n, n, body.nv).clone()
    q[..., i] = x[None, :]
    q[..., j] = y[:, None]
    with torch.no_grad():
        chi = FieldBasis(eta[None], K[None], kind="full")(q)[..., 0, :]
        p = dynamics.tip_position(body, q)
        F = hand_force(body, q, chi)
    return {"x": _np(x), "y": _np(y), "q": _np(q), "chi": _np(chi), "p": _np(p), "F": _np(F)}


def _label(body: Body, k: int) -> str:
    return coordinate_names(body)[k]


def field_figure(body: Body, eta, K, dims=(0, 3), q_ref=None, title: str = "",
                 axes=None, span=None) -> plt.Figure:
    """Thesis figure 3-1 for one field (:func:`field_slice`; eta (nv), K (nv×nv)).

    Left: the slice of joint space through q_ref along ``dims`` = (i, j), isocontours of
    the torque magnitude |χ| over all nv components and arrows (χ_i, χ_j). Right: the
    hand force field for the same postures: hand positions p(q) and forces
    F = (Jᵀ)⁺χ(q) (:func:`hand_force`), both projected onto the plane of largest spread
    of the positions (their first two principal directions e₁, e₂); grey lines are
    the images of the slice's grid lines, dark grey the arm at q_ref. ``axes``: a pair
    of 2-D axes to draw into (the title then heads both panels), else a new figure;
    ``span``: the slice's half-width, as in :func:`field_slice`."""
    s = field_slice(body, eta, K, dims, q_ref, span)
    i, j = dims
    own = axes is None
    if own:
        fig, axes = plt.subplots(1, 2, figsize=(11, 4.8))
        fig.suptitle(title)
        head = ""
    else:
        fig = axes[0].figure
        head = f"{title}\n" if title else ""
    ax, bx = axes
    X, Y = np.meshgrid(s["x"], s["y"])
    mag = np.linalg.norm(s["chi"], axis=-1)
    cs = ax.contour(X, Y, mag, levels=8, cmap="viridis", linewidths=0.9)
    ax.clabel(cs, fontsize=6, fmt="%.2g")
    k = slice(None, None, 2)
    ax.quiver(X[k, k], Y[k, k], s["chi"][k, k, i], s["chi"][k, k, j], color="C3", width=0.004)
    eta_np = _np(torch.as_tensor(eta, dtype=torch.float64))
    ax.plot(eta_np[i], eta_np[j], "k+", ms=10, label="η")
    ax.set_xlabel(f"{_label(body, i)} (rad)")
    ax.set_ylabel(f"{_label(body, j)} (rad)")
    ax.set_title(f"{head}contours |χ| (all {body.nv} components), arrows (χ_{i}, χ_{j})", fontsize=9)
    ax.set_aspect("equal")
    ax.legend(fontsize=7, loc="upper right")

    p = s["p"].reshape(-1, 3)
    c = p.mean(0)
    e = np.linalg.svd(p - c)[2][:2]           # e₁, e₂: rows, the two largest spreads
    e *= np.sign(e[np.arange(2), np.abs(e).argmax(1)])[:, None]
    P = (s["p"] - c) @ e.T
    Fp = s["F"] @ e.T
    for r in range(0, P.shape[0], 2):
        bx.plot(P[r, :, 0], P[r, :, 1], color="0.8", lw=0.6)
        bx.plot(P[:, r, 0], P[:, r, 1], color="0.8", lw=0.6)
    bx.quiver(P[k, k, 0], P[k, k, 1], Fp[k, k, 0], Fp[k, k, 1], color="C0", width=0.004)
    ref = _np(torch.as_tensor(eta if q_ref is None else q_ref, dtype=torch.float64))
    arm_pts = (joint_positions(body, ref[None])[0] - c) @ e.T
    bx.plot(arm_pts[:, 0], arm_pts[:, 1], "o-", color="0.35", ms=3, label="arm at q_ref")
    tip_eta = (joint_positions(body, eta_np[None])[0, -1] - c) @ e.T
    bx.plot(tip_eta[0], tip_eta[1], "k*", ms=9, label="hand at η")
    for a in (0, 1):
        v = ", ".join(f"{round(t, 2) + 0.0:.2f}" for t in e[a])
        (bx.set_xlabel if a == 0 else bx.set_ylabel)(f"e{a + 1} = ({v}) (m)", fontsize=8)
    bx.set_title(f"{head}hand force F = (Jᵀ)⁺χ, plane of largest spread", fontsize=9)
    bx.set_aspect("equal", adjustable="datalim")
    bx.legend(fontsize=7, loc="upper right")
    if own:
        fig.tight_layout()
    return fig


def gallery_fields(nv: int = 7) -> list:
    """The examples of :func:`fields_gallery`: [(label, η (nv), K (nv×nv))], one field of
    each stiffness kind centred on the thesis' "come here" posture (shoulder −π/2 about
    x, elbow −π/2, wrist −π/4): scalar K = 1.5 I; diagonal, stiff in the shoulder
    (3) and soft in the elbow (0.75); full, 2 on the shoulder-x and elbow diagonal with
    coupling 1.2 between them (eigenvalues 0.8 and 3.2 in that plane, so the contours
    are ellipses tilted by 45°)."""
    eta = torch.zeros(nv, dtype=torch.float64)
    eta[[0, 3, 4]] = torch.tensor([-torch.pi / 2, -torch.pi / 2, -torch.pi / 4], dtype=torch.float64)
    eye = torch.eye(nv, dtype=torch.float64)
    diag = eye.clone()
    diag[0, 0], diag[3, 3] = 3.0, 0.75
    full = eye.clone()
    full[0, 0] = full[3, 3] = 2.0
    full[0, 3] = full[3, 0] = 1.2
    return [("scalar K = 1.5 I", eta, 1.5 * eye), ("diagonal K", eta, diag),
            ("full K (shoulder x–elbow coupling)", eta, full)]


def fields_gallery(body: Body) -> plt.Figure:
    """Three fields (:func:`gallery_fields`: scalar, diagonal, full K), one row each, as
    :func:`field_figure` draws them on the shoulder-x/elbow slice through η."""
    examples = gallery_fields(body.nv)
    fig, axes = plt.subplots(len(examples), 2, figsize=(11, 4.6 * len(examples)), squeeze=False)
    for row, (label, eta, K) in zip(axes, examples):
        field_figure(body, eta, K, dims=(0, 3), title=label, axes=row)
    fig.tight_layout()
    return fig


def profiles_figure() -> plt.Figure:
    """Thesis figure 3-2: the smooth step ψ(u) and the cosine pulse φ(u) for u ∈ [−0.2, 1.2]
    (:func:`tflearn.model.fields.step_profile`, :func:`tflearn.model.fields.pulse_profile`)."""
    from ..model.fields import pulse_profile, step_profile
    u = torch.linspace(-0.2, 1.2, 281, dtype=torch.float64)
    fig, ax = plt.subplots(figsize=(6, 3.6))
    ax.plot(_np(u), _np(step_profile(u)), label=r"step $\psi(u) = u - \sin(2\pi u)/2\pi$ on [0, 1]")
    ax.plot(_np(u), _np(pulse_profile(u)), "--",
            label=r"pulse $\varphi(u) = \frac{1}{2}(1 - \cos 2\pi u)$ on [0, 1]")
    for edge in (0.0, 1.0):
        ax.axvline(edge, color="0.7", lw=0.6)
    ax.set_xlabel("u = (t − onset) / duration")
    ax.set_title("time profiles (ψ: 0 before, 1 after; φ: 0 outside [0, 1])", fontsize=9)
    ax.set_ylim(-0.05, 1.45)
    ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    return fig


def weights_bars(names, a, b, title: str = "") -> plt.Figure:
    """Per-motion weights as grouped bars: one group per motion (N), and in each, for every
    field i (M), the step weight a_ji (solid) and the pulse weight b_ji (hatched) side by
    side. a, b (N×M)."""
    a, b = _np(a), _np(b)
    N, M = a.shape
    w = 0.8 / (2 * M)
    x = np.arange(N)
    fig, ax = plt.subplots(figsize=(max(5.0, 0.5 + 0.35 * N * M), 3.8))
    for i in range(M):
        off = (2 * i - M + 0.5) * w
        ax.bar(x + off, a[:, i], w, color=f"C{i % 10}", label=f"a, field {i}")
        ax.bar(x + off + w, b[:, i], w, facecolor="white", edgecolor=f"C{i % 10}", hatch="///",
               label=f"b, field {i}")
    ax.set_xticks(x, list(names), rotation=30, ha="right", fontsize=8)
    ax.set_ylabel("weight")
    ax.set_title(title)
    ax.legend(fontsize=7, ncol=min(M, 4))
    fig.tight_layout()
    return fig


def learning_curves(curves: dict, title: str = "", ylabel: str = "relative torque cost") -> plt.Figure:
    """One line per label of ``curves`` (label → values per step) against the step
    number, on a log y axis (non-positive values are not drawn)."""
    fig, ax = plt.subplots(figsize=(6, 3.8))
    for label, values in curves.items():
        ax.plot(np.arange(len(values)), np.asarray(values, dtype=float), label=label)
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(True, which="both", lw=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def link_segments(body: Body, q, base=None) -> np.ndarray:
    """Each link drawn as a segment from its joint to its far end (...×L×2×3, m): a
    cylinder's end (0, 0, −length) in its frame, for a general link twice its centre of
    mass (the far end of a uniform segment, e.g. a bone of :mod:`tflearn.mocap.skeleton`). Unlike
    :func:`joint_positions` this draws branching trees and closed loops correctly.
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


# ------------------------------------------------------------------ perturbations

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
