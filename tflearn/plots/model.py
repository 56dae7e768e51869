"""Matplotlib figures of the model (thesis figures 3-1 and 3-2): a field on a slice of joint
space and the hand forces it makes, the time profiles, per-motion weights and learning curves.

Axes carry their units as :mod:`tflearn.plots.figures` (coordinates in rad, positions in m).
"""
from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np
import torch

from ..model.fields import FieldBasis, as_float
from ..model.weights import pulse_profile, step_profile
from ..physics import dynamics
from ..physics.body import Body
from .figures import _np, coordinate_names, joint_positions


def hand_force(body: Body, q, tau) -> torch.Tensor:
    """The hand force F (...×3) whose joint torques Jᵀ F best match τ: F = (Jᵀ)⁺ τ.

    J (...×3×nv) is the hand tip's Jacobian in the body's velocity coordinates, ṗ = J v
    (the linear rows of :func:`tflearn.physics.dynamics.point_jacobian` at the body's tip;
    for ball joints the geometric Jacobian of child-frame angular velocities, not ∂p/∂ν),
    at q (...×nv), and τ (...×nv) is dual to the velocities (power τ·v = F·ṗ). F minimises
    ‖Jᵀ F − τ‖ (the minimum-norm minimiser where J loses rank); where J has full row rank
    F = (J Jᵀ)⁻¹ J τ, and Jᵀ F = τ exactly whenever τ is a torque some hand force produces
    (τ in the range of Jᵀ)."""
    q = torch.as_tensor(q, dtype=torch.float64)
    Jt = dynamics.point_jacobian(body, q, body.tip_link, body.tip_point)[..., :3, :].transpose(-1, -2)
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
    (:func:`tflearn.model.weights.step_profile`, :func:`tflearn.model.weights.pulse_profile`)."""
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


def knee(path: list, chosen: int, motions: int, title: str = "") -> plt.Figure:
    """The shared basis' model selection (:func:`tflearn.fit.select.select`): for each
    size m of the forward selection ``path`` ([m, Σ_j C_j, motions served]), the summed
    relative torque cost (log) and the motions served, ``chosen`` marked."""
    m, cost, served = (np.array(c, dtype=float) for c in zip(*path)) if path else ([], [], [])
    fig, ax = plt.subplots(figsize=(6, 3.4))
    ax.semilogy(m, np.maximum(cost, 1e-300), "o-", color="C0")
    ax.set_xlabel("fields M")
    ax.set_ylabel("summed relative torque cost", color="C0")
    right = ax.twinx()
    right.plot(m, served, "s--", color="C1")
    right.set_ylabel(f"motions served (of {motions})", color="C1")
    right.set_ylim(0, motions * 1.05)
    ax.axvline(chosen, color="k", lw=0.8, ls=":")
    ax.set_title(title or f"choosing the shared basis: M = {chosen}")
    fig.tight_layout()
    return fig
