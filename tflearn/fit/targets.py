"""Motions prepared for fitting: padded tensors of samples, velocities and torques."""
from __future__ import annotations

import math
from dataclasses import dataclass, fields, is_dataclass, replace
from typing import Optional

import torch

from ..model.fields import FieldBasis
from ..model.program import FieldProgram
from ..model.weights import MotionWeights
from ..motions import spline
from ..motions.torso import Bases
from ..physics import dynamics
from ..physics.body import Body
from ..simulation.simulate import SimOptions, simulate


@dataclass
class Targets:
    """N motions, each shifted to start at t = 0 and padded to a common length T.

    names (N); t (N×T) sample times; mask (N×T) real samples; w (N×T) trapezoid
    quadrature weights (zero on padding); wt (N×T) the same without the ``trim`` samples
    at each end, where spline torques are least reliable (used by torque costs);
    q, v, tau (N×T×n) coordinates, body velocities and inverse-dynamics torques;
    duration (N); q0, qd0 (N×n); grid (G) the union of all
    sample times, index (N×T) each sample's position in it (for batched simulation);
    coord_weight (N×n) or None: each coordinate's weight ω in the torque costs,
    Σ_t w Σ_k ω_k (τ_k − F_k)² (None: ω = 1, the thesis' cost; :func:`inertia_weights`
    measures torque errors by the accelerations they cause); base: each motion's moving
    base (:class:`tflearn.motions.torso.Bases`, N members, motion time t at its base's
    start + t), which its torques include and its simulations ride on, or None (fixed)."""

    names: list
    t: torch.Tensor
    mask: torch.Tensor
    w: torch.Tensor
    wt: torch.Tensor
    q: torch.Tensor
    v: torch.Tensor
    tau: torch.Tensor
    duration: torch.Tensor
    q0: torch.Tensor
    qd0: torch.Tensor
    grid: torch.Tensor
    index: torch.Tensor
    coord_weight: Optional[torch.Tensor] = None
    base: Optional[Bases] = None

    @property
    def N(self) -> int:
        return len(self.names)

    @property
    def rate(self) -> torch.Tensor:
        """Samples per second of each motion (N), as :attr:`tflearn.motions.motion.Motion.rate`."""
        return (self.mask.sum(-1) - 1) / self.duration

    def torque_scale(self) -> torch.Tensor:
        """Σ_t w Σ_k ω_k τ_k² per motion (N): the normaliser of relative torque costs."""
        return (self.wt * (self.weigh(self.tau) ** 2).sum(-1)).sum(-1).clamp_min(1e-12)

    def weigh(self, x: torch.Tensor) -> torch.Tensor:
        """√ω ⊙ x for torques x (N×T×n) or design columns (N×T×n×X): the residual of a
        coordinate-weighted torque cost; x itself when :attr:`coord_weight` is None."""
        if self.coord_weight is None:
            return x
        s = self.coord_weight.sqrt()[:, None, :]
        return x * (s if x.ndim == 3 else s[..., None])

    def to(self, device) -> Targets:
        """The same targets with every tensor, its base's too, on ``device``."""
        return _on(self, torch.device(device))

    def select(self, idx, trim: bool = False) -> Targets:
        """The targets of some motions (a list of indices), on their own time grid (the
        union of their sample times only, so a simulation of them ends with the longest
        of them); ``trim``: padded only to the longest of them (T shorter)."""
        idx = torch.as_tensor(idx, dtype=torch.long)
        T = int(self.mask[idx].any(0).nonzero().max()) + 1 if trim else self.mask.shape[1]
        sub = {k: getattr(self, k)[idx, :T] for k in ("t", "mask", "w", "wt", "q", "v", "tau")}
        sub.update({k: getattr(self, k)[idx] for k in ("duration", "q0", "qd0")})
        if self.coord_weight is not None:
            sub["coord_weight"] = self.coord_weight[idx]
        if self.base is not None:
            sub["base"] = self.base.take(idx)
        grid, index = union_grid(sub["t"])
        return Targets(names=[self.names[i] for i in idx.tolist()], grid=grid, index=index, **sub)


def _on(x, device):
    """x with every tensor in it (a dataclass' fields, recursively) on ``device``."""
    if isinstance(x, torch.Tensor):
        return x.to(device)
    if is_dataclass(x):
        return replace(x, **{f.name: _on(getattr(x, f.name), device) for f in fields(x)})
    return x


CHUNK_BYTES = 1 << 28
"""What one chunk of motions' per-sample arrays may hold (bytes): :func:`chunks`."""


def chunks(tg: Targets, width: int, keys: Optional[list] = None) -> list:
    """The motions cut into chunks (lists of indices), motions of like length together
    (longest first), each chunk's per-sample arrays of ``width`` float64 columns per
    torque entry (chunk × its longest T × n × width) under :data:`CHUNK_BYTES`, at least
    one motion per chunk; one chunk of every motion, in order, when they all fit.
    ``keys`` (N, sortable): motions of one key together, a chunk never holding two.
    Design matrices and Jacobians of many motions are built a chunk at a time (with
    :meth:`Targets.select` ``trim``), so that memory stays bounded and padding small."""
    per = 8 * tg.tau.shape[-1] * width                 # bytes per sample
    lengths = tg.mask.sum(-1).tolist()
    if tg.N * tg.mask.shape[1] * per <= CHUNK_BYTES:
        return [list(range(tg.N))]
    keys = [()] * tg.N if keys is None else keys
    out, part = [], []
    for j in sorted(range(tg.N), key=lambda j: (keys[j], -lengths[j], j)):
        if part and (keys[j] != keys[part[0]] or (len(part) + 1) * lengths[part[0]] * per > CHUNK_BYTES):
            out.append(part)
            part = []
        part.append(j)
    return out + [part]


def union_grid(t: torch.Tensor):
    """The sorted union of all sample times (G) and each sample's index in it (N×T);
    times are compared to 1e-9 s."""
    return torch.unique(torch.round(t * 1e9) / 1e9, sorted=True, return_inverse=True)


def simulate_targets(body: Body, basis: FieldBasis, weights: MotionWeights, tg: Targets,
                     options: SimOptions = SimOptions(), motions=None):
    """Every motion simulated from its own initial state under its own program, in one
    batched ``odeint`` over the union grid: (q, v) at each motion's samples (N×T×n each).
    ``motions``: the indices into ``weights`` of the motions ``tg`` holds (a
    :meth:`Targets.select` of them; default: ``weights``' motions are ``tg``'s), so that
    gradients reach the whole ``weights``.
    Raises :class:`~tflearn.simulation.simulate.SimulationFailed` when the batch cannot go on."""
    tr = simulate(body, FieldProgram(basis, weights, index=motions), tg.q0, tg.qd0, tg.grid, options,
                  base=tg.base)
    return on_samples(tg, tr.q), on_samples(tg, tr.v)


def on_samples(tg: Targets, x: torch.Tensor) -> torch.Tensor:
    """Each motion's own samples (N×T×k) of a path on the union grid (N×G×k)."""
    return x.gather(1, tg.index.unsqueeze(-1).expand(-1, -1, x.shape[-1]))


def submovement_windows(tg: Targets, P: int, spread: float = 0.25, rate: float = 0.0):
    """P sub-movement windows per motion from its joint speed s(t) = ‖v(t)‖ (onsets,
    durations: N×P each, for :class:`~tflearn.model.weights.MotionWeights`): the motion is cut at
    the P − 1 slowest interior local minima of s (a sub-movement ends where the limb
    nearly stops; minima within 5% of either end are ignored), the longest pieces halved
    while minima are missing, and window k spans its piece [t_k, t_{k+1}] widened by
    ``spread`` of its length on each side (a pulse peaks mid-piece and overlaps its
    neighbours, so the windows' sum has no gaps). With ``rate`` > 0 (windows per second)
    motion j is cut into P_j = min(P, ⌈rate·λ_j⌉) pieces, λ_j its duration, and its other
    P − P_j windows start 1 s after its end: their pulses are 0 all along it, so their
    columns of the torque design are 0 and their weights stay 0 (a motion is described
    by as many windows as its length asks, whatever the longest motion's P)."""
    onsets, lengths = [], []
    for j in range(tg.N if P else 0):
        m = tg.mask[j]
        t, speed = tg.t[j][m], tg.v[j][m].norm(dim=-1)
        T = len(t)
        mine = min(P, max(1, math.ceil(rate * float(tg.duration[j]) - 1e-9))) if rate else P
        interior = [k for k in range(1, T - 1) if speed[k] < speed[k - 1] and speed[k] <= speed[k + 1]
                    and 0.05 * t[-1] < t[k] < 0.95 * t[-1]]
        cuts = sorted(sorted(interior, key=lambda k: float(speed[k]))[:mine - 1])
        bounds = [float(t[0])] + [float(t[k]) for k in cuts] + [float(t[-1])]
        while len(bounds) < mine + 1:
            k = max(range(len(bounds) - 1), key=lambda i: bounds[i + 1] - bounds[i])
            bounds.insert(k + 1, 0.5 * (bounds[k] + bounds[k + 1]))
        piece = [hi - lo for lo, hi in zip(bounds[:-1], bounds[1:])]
        after = P - mine                              # windows past its end
        onsets.append([lo - spread * d for lo, d in zip(bounds[:-1], piece)] + [float(t[-1]) + 1.0] * after)
        lengths.append([(1 + 2 * spread) * d for d in piece] + [1.0] * after)
    z = dict(dtype=torch.float64)
    return torch.tensor(onsets, **z).reshape(tg.N, P), torch.tensor(lengths, **z).reshape(tg.N, P)


def trapezoid(t: torch.Tensor) -> torch.Tensor:
    """The trapezoid rule's weights at sample times t (T): Σ w f ≈ ∫ f dt."""
    dt = t[1:] - t[:-1]
    w = torch.zeros_like(t)
    w[:-1] += dt / 2
    w[1:] += dt / 2
    return w


def prepare(body: Body, motions: list, trim: int = 5, weight: str = "uniform",
            base: Optional[Bases] = None) -> Targets:
    """Inverse-dynamics torques and padded tensors for a list of :class:`~tflearn.motions.motion.Motion`.

    ``trim`` samples at each end of a motion are left out of torque costs: a spline's
    second derivative is weakest at its ends, and a fast motion sampled at 100 Hz can
    give end torques far from the true ones. ``weight``: the torque costs' coordinate
    weights, ``uniform`` (the thesis' cost) or ``inertia`` (:func:`inertia_weights`).
    ``base``: the motions' moving bases (:class:`tflearn.motions.torso.Bases`, one per motion,
    each at its motion's first sample at t = 0, as :attr:`Targets.base`): the torques
    are those on them."""
    if not motions:
        raise ValueError("prepare: no motions")
    N, T, n = len(motions), max(len(m.t) for m in motions), body.nv
    z = dict(dtype=torch.float64)
    t = torch.zeros(N, T, **z)
    mask = torch.zeros(N, T, dtype=torch.bool)
    w = torch.zeros(N, T, **z)
    q, v, tau = (torch.zeros(N, T, n, **z) for _ in range(3))
    if base is not None and base.B != N:
        raise ValueError(f"prepare: {base.B} moving bases for {N} motions")
    for j, m in enumerate(motions):
        k = len(m.t)
        tj = torch.as_tensor(m.t, **z)
        seen = None if base is None else base.take(torch.full((k,), j)).terms(body.gravity, tj - tj[0])
        tau_j, vel_j, _ = spline.torques(body, m, base=seen)
        t[j, :k] = tj - tj[0]
        t[j, k:] = t[j, k - 1]
        mask[j, :k] = True
        w[j, :k] = trapezoid(tj)
        q[j, :k] = torch.as_tensor(m.q, **z)
        v[j, :k] = torch.as_tensor(m.qd, **z) if m.qd is not None else vel_j
        tau[j, :k] = tau_j
        q[j, k:], v[j, k:], tau[j, k:] = q[j, k - 1], v[j, k - 1], tau[j, k - 1]
    grid, inverse = union_grid(t)
    duration = t.amax(-1)
    wt = w.clone()
    for j, m in enumerate(motions):
        k = len(m.t)
        if k > 4 * trim:
            wt[j, :trim] = 0
            wt[j, k - trim:k] = 0
    tg = Targets(names=[m.name for m in motions], t=t, mask=mask, w=w, wt=wt, q=q, v=v, tau=tau,
                 duration=duration, q0=q[:, 0].clone(), qd0=v[:, 0].clone(),
                 grid=grid, index=inverse, base=base)
    if weight not in ("uniform", "inertia"):
        raise ValueError(f"prepare: weight must be 'uniform' or 'inertia', not {weight!r}")
    return replace(tg, coord_weight=inertia_weights(body, tg)) if weight == "inertia" else tg


def mean_inertia(body: Body, tg: Targets) -> torch.Tensor:
    """Each motion's mean joint-space inertia along its path, m̄_k = mean_t M(ν_t)_kk
    over its real samples (N×n; kg·m² for rotations)."""
    diag = torch.diagonal(dynamics.mass_matrix(body, tg.q), dim1=-2, dim2=-1)       # N×T×n
    m = tg.mask.unsqueeze(-1).to(diag.dtype)
    return (diag * m).sum(1) / m.sum(1)


def inertia_weights(body: Body, tg: Targets) -> torch.Tensor:
    """ω_k = 1/m̄_k (N×n, :func:`mean_inertia`): a torque error weighted so, ω_k e_k², is
    e_k · (the acceleration it causes alone), so that the light wrist counts as much as
    the shoulder — with the thesis' uniform weights a relative torque cost of 1% can hide
    a wrist that is not driven at all, the shoulder's torques being 10–100× larger."""
    return 1.0 / mean_inertia(body, tg)
