"""Path matching of each motion's activations by multiple shooting and Levenberg–Marquardt.

With the basis fixed, motion j's path depends on its own parameters θ_j only (its
weights a, b, c and, optionally, its activation timing), so the problem splits into one
small least-squares problem per motion. The fields may be freed too
(``ShootingOptions.fields``: θ then also holds every field's centre and free stiffness
parameters, :meth:`~tflearn.model.fields.FieldBasis.free_vector`): the fields of a motion whose
path amplifies small field errors several hundredfold are placed by its path, not by
torque matching on spline torques (docs/model.md, "Programs whose motion is chaotic").

**Shared fields.** With the fields free and several motions, the fields are one
parameter vector f shared by every motion, and the problem no longer splits: one
Levenberg–Marquardt problem over (θ_1, …, θ_N, f), whose normal equations are
arrow-shaped — each motion's weights couple with f only,

    [ J_jᵀJ_j (weights)   J_jᵀJ_j (weights, f)  ]      A_ff = Σ_j J_jᵀJ_j (f, f),
    [ (its transpose)     A_ff                  ]

J_j motion j's Jacobian (:meth:`_Problem.jacobian`, the same forward differences: a
perturbation of f is one of every motion's copies) —, one μ for all, a step kept when
it lowers the summed cost, and the whole θ backed off towards θ₀ where a new horizon
cannot be simulated; at the end the summed path loss is never worse than at the start.

**Segments.** Motion j is cut every K_j = max(1, round(h·rate_j)) samples; segment s
starts at the target's own state (q, v) at its first sample k_s and is simulated to
sample k_s + K_j under the motion's program at the motion's own time t_{k_s} + τ
(:class:`~tflearn.model.program.FieldProgram`'s ``start``). Its residuals at every sample but
its first are

    r = √(w_t / λ_j) · [e_t ;  √β (v_sim,t − v_target,t) ;  √γ (p(q_sim,t) − p(q_target,t))],
    e_t = q_sim,t ⊖ q_target,t

(w_t the trapezoid weights, λ_j the duration, p the hand tip's position), so that with
γ = 0 (the default) Σ r² is the path loss of :func:`tflearn.fit.path.path_loss` with each
segment restarted on the target; γ > 0 (rad²/m²) also counts where the hand is, the
distance the success bar measures. Drift
cannot build up over a short segment, so the residuals stay nearly linear in θ.

**Horizon.** Segments start at h = ``ShootingOptions.horizon`` and double, joining
pairwise, until one segment spans each motion: the last stage minimises the path loss
itself (single shooting) from a point found where the problem was well-conditioned.
A motion whose segments cannot be simulated at a new horizon from the parameters the
last stage left is not dropped: it goes back towards its starting parameters θ₀, to
θ₀ + α(θ − θ₀) for the first α of ½, ¼, …, 1/16, 0 that can be simulated, and the stage
goes on from there. θ₀ simulates the whole motion (else the motion is not fitted at all),
so the last stage always has a point to start from.

**Steps.** At each stage, Levenberg–Marquardt with Marquardt's scaling: δ solves
(JᵀJ + μ diag(JᵀJ)) δ = −Jᵀr over the parameters not held at a bound (a, b, c ≥ 0,
durations ≥ 10 ms; a parameter at its bound whose gradient points out stays there), the
step is projected onto the bounds and kept if it lowers the motion's cost (μ ÷ 3), else
μ × 4 and the step is tried again. Every motion has its own μ and its own decisions.
With ``ShootingOptions.sparse`` the weights at 0 when shooting starts are held there.

**Jacobian.** Forward differences of D + 1 copies of every segment (D = len(θ_j)),
simulated in one batch: the copies of a segment share every step of the adaptive solver
(one group of :func:`tflearn.simulation.simulate.simulate`, each segment on its own steps; with a
solver other than dopri5 the whole batch shares them), so their differences are those
of one discrete map — no step-size noise — and agree with backpropagation through
``odeint`` (tests/test_shooting.py). One simulation per Jacobian, whatever the number
of motions; parameters that every motion of the batch holds (``ShootingOptions.sparse``)
get no copy. With ``ShootingOptions.broyden`` they are taken at each stage's start
only: after a step that lowers a motion's cost its J is updated by Broyden's rank-one
formula from the residuals that step's trial already simulated,
J ← J + (Δr − J δ) δᵀ / δᵀδ, so that an iteration costs one simulation of the segments
instead of D + 1 of them; differences are taken again where the step's fall was less
than a quarter of what J predicted (ρ < 1/4), where a step from an updated J fails, and
before a motion may leave a stage (only differences say that it no longer gains).

**Never worse.** A motion whose path loss (single shooting) ends above where it started
— the short horizons minimise a different cost — gets its starting parameters back.

**Failures** are data: a simulation that fails rejects the step (as a larger μ) for the
motions of its batch, which are then simulated one by one so that one motion's failure
does not stop the others; a motion whose Jacobian cannot be simulated stops where it is,
and :attr:`ShootingResult.failures` says why.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Callable, Optional

import torch

from .. import parallel
from ..model.fields import FieldBasis, MotionFields
from ..model.program import FieldProgram
from ..model.weights import MotionWeights
from ..motions.torso import Bases
from ..physics.body import Body
from ..physics.configspace import difference
from ..physics.dynamics import tip_position
from ..simulation.simulate import SimOptions, SimulationFailed, simulate
from .targets import Targets, union_grid

WEIGHTS = ("a_raw", "b_raw", "c_raw")
TIMING = MotionWeights.TIMING + MotionWeights.WINDOWS
_DURATIONS = ("step_duration", "pulse_duration", "window_duration")


@dataclass(frozen=True)
class ShootingOptions:
    """horizon: the first segments' length h (s), doubled at each stage until one segment
    spans each motion; iterations: Levenberg–Marquardt iterations per stage (a motion
    leaves a stage sooner once its cost falls by less than ``tol`` relatively in an
    iteration, or is below ``floor`` (rad²: a path RMSE of 1e-5 rad)); phases: also fit
    each motion's activation timing (onsets and durations of its steps, pulses and
    windows); velocity_weight: β; tip_weight: γ (rad²/m²: γ = 100 counts 1 cm of hand
    like 0.1 rad of joint angle); mu: the initial damping; step: the relative
    forward-difference step; fields: also fit the basis' fields (shared by the motions,
    module docstring); broyden: after a successful step update J by Broyden's
    formula instead of differences (module docstring); used: fit each motion alone on
    the fields it has a weight on (a, b or c > 0), its weights on the others held at 0:
    D ∝ those fields, not M, for a basis of many fields (not with ``fields``); free:
    with ``fields``, the fields freed (indices; None: every field), the others held;
    sparse: a weight at 0 when shooting starts stays at 0, so that a sparse program
    (``Impedance.sparsity``) keeps its support and only its non-zero weights move;
    windows: only the weights of these sub-movement windows move (indices; None: every
    weight), a, b, the other windows and the timing held; receding: a motion with
    windows longer than this (s; None: none) is fitted window by window from its own
    simulation instead (:func:`.receding.receding_match`, where ``horizon``, ``phases``,
    ``fields``, ``broyden`` and ``used`` do not apply; :func:`tflearn.synthesis.shoot`
    sends it there), ``ahead`` windows beyond each fitted with it."""

    horizon: float = 0.25
    iterations: int = 6
    tol: float = 1e-3
    floor: float = 1e-10
    phases: bool = False
    velocity_weight: float = 0.1
    tip_weight: float = 0.0
    mu: float = 1e-3
    step: float = 1e-6
    fields: bool = False
    broyden: bool = False
    used: bool = False
    free: Optional[tuple] = None
    sparse: bool = False
    windows: Optional[tuple] = None
    receding: Optional[float] = None
    ahead: int = 1


@dataclass
class ShootingResult:
    """loss: each motion's path loss at the end (single shooting, N; ∞ where it cannot be
    simulated); history: one row per Levenberg–Marquardt iteration, {"horizon", "cost"
    (N, the stage's multiple-shooting cost)}; failures: {motion name: why it stopped
    early}; simulations: how many batched simulations were run."""

    loss: list
    history: list = field(default_factory=list)
    failures: dict = field(default_factory=dict)
    simulations: int = 0


@dataclass
class _Segments:
    """The segments of one stage: motion (B), start time t0 (B), initial state q0, v0
    (B×n), sample index (B×(K+1)) into the motion's samples, residual weight (B×(K+1):
    0 at each segment's first sample and past the motion's end), local grid (G) and each
    sample's position in it (B×(K+1))."""

    motion: torch.Tensor
    t0: torch.Tensor
    q0: torch.Tensor
    v0: torch.Tensor
    sample: torch.Tensor
    weight: torch.Tensor
    grid: torch.Tensor
    index: torch.Tensor
    base: Optional[Bases] = None

    def take(self, idx: torch.Tensor) -> _Segments:
        """The segments ``idx`` (indices), on the same grid."""
        return _Segments(self.motion[idx], self.t0[idx], self.q0[idx], self.v0[idx], self.sample[idx],
                         self.weight[idx], self.grid, self.index[idx],
                         None if self.base is None else self.base.take(idx))


def segments(tg: Targets, horizon: float, motions=None) -> _Segments:
    """The multiple-shooting segments of length ``horizon`` (s) of ``motions`` (indices,
    default all), see the module docstring. Every segment holds K + 1 samples, K the most
    that any motion of ``tg`` takes, whichever ``motions`` are asked for: a motion's
    residuals are then the same beside any others (a Jacobian from one batch, residuals
    from another, :func:`_broyden`)."""
    motions = range(tg.N) if motions is None else motions
    L = tg.mask.sum(-1).tolist()                                        # samples per motion
    counts = [max(1, min(L[j] - 1, round(horizon * float(tg.rate[j])))) for j in range(tg.N)]
    rows = [(j, k0, counts[j]) for j in motions for k0 in range(0, L[j] - 1, counts[j])]
    K = max(counts)
    motion = torch.tensor([r[0] for r in rows])
    k0 = torch.tensor([r[1] for r in rows])
    offset = torch.arange(K + 1)
    length = torch.tensor([min(r[2], L[r[0]] - 1 - r[1]) for r in rows])
    sample = k0[:, None] + offset.clamp(max=length[:, None])           # B×(K+1), clamped at the end
    inside = (offset > 0) & (offset <= length[:, None])
    weight = torch.where(inside, tg.w[motion[:, None], sample], torch.zeros(()))
    weight = weight / tg.duration[motion, None]
    t0 = tg.t[motion, k0]
    grid, index = union_grid(tg.t[motion[:, None], sample] - t0[:, None])
    base = None if tg.base is None else tg.base.take(motion, shift=t0)
    return _Segments(motion, t0, tg.q[motion, k0], tg.v[motion, k0], sample, weight, grid, index, base)


def _simulate(body, basis, weights: MotionWeights, seg: _Segments, options: SimOptions,
              copies: int = 1):
    """(q, v) of every segment (copies·B × (K+1) × n) under ``weights``, whose rows are
    copy c's motion of segment b at row c·B + b; raises SimulationFailed."""
    rep = lambda x: x.repeat((copies,) + (1,) * (x.ndim - 1))
    program = FieldProgram(basis, weights, start=rep(seg.t0))
    groups = rep(torch.arange(len(seg.motion))) if options.batch == "each" else None
    base = None if seg.base is None else seg.base.take(torch.arange(len(seg.motion)).repeat(copies))
    tr = simulate(body, program, rep(seg.q0), rep(seg.v0), seg.grid, options, groups=groups, base=base)
    idx = rep(seg.index).unsqueeze(-1).expand(-1, -1, body.nv)
    return tr.q.gather(1, idx), tr.v.gather(1, idx)


def _residuals(body, tg: Targets, seg: _Segments, q, v, beta: float, gamma: float = 0.0) -> torch.Tensor:
    """r (…×B×R) for simulated (q, v) of the segments (…×B×(K+1)×n), see the module
    docstring."""
    target = tg.q[seg.motion[:, None], seg.sample]
    e = difference(body, target, q)
    ev = v - tg.v[seg.motion[:, None], seg.sample]
    s = seg.weight.sqrt().unsqueeze(-1)
    parts = [(s * e).flatten(-2), (math.sqrt(beta) * s * ev).flatten(-2)]
    if gamma:
        ep = tip_position(body, q) - tip_position(body, target)
        parts.append((math.sqrt(gamma) * s * ep).flatten(-2))
    return torch.cat(parts, dim=-1)


class _Problem:
    """The motions' parameters θ (N×D, the layout of :meth:`MotionWeights.flat` over
    ``keys``, followed with ``opts.fields`` by the fields' :meth:`FieldBasis.free_vector`),
    their bounds, and the simulations of segments at one θ."""

    def __init__(self, body, basis, weights, tg, keys, opts: ShootingOptions, sim: SimOptions,
                 distributed: bool = False):
        self.body, self.basis, self.weights, self.tg = body, basis, weights, tg
        self.distributed = distributed and parallel.size() > 1
        # the copies of a segment must share every step (one discrete map): one group each
        # (dopri5), else the whole batch on shared steps
        self.keys, self.opts = keys, opts
        self.sim = replace(sim, batch="each" if sim.can_step_each else "shared")
        self.simulations = 0
        layout = [(k, math.prod(getattr(weights, k).shape[1:])) for k in keys]
        self.lower = torch.cat([torch.full((d,), 1e-2 if k in _DURATIONS else
                                           (0.0 if k in WEIGHTS else -math.inf), dtype=torch.float64)
                                for k, d in layout])
        self.dw = len(self.lower)                  # θ[:dw] the weights, θ[dw:] the fields
        self.free = list(range(basis.M)) if opts.free is None else list(opts.free)
        if opts.fields:
            free = torch.full((len(self.free) * basis.free_size,), -math.inf, dtype=torch.float64)
            self.lower = torch.cat([self.lower, free])
        weight = torch.cat([torch.full((d,), k in WEIGHTS) for k, d in layout]
                           + [torch.zeros(len(self.lower) - self.dw, dtype=torch.bool)])
        # the parameters held where they start (N×D): those of windows that start after
        # their motion's end (no sample sees them); with opts.sparse, the weights at 0;
        # with opts.windows, all but those windows' weights
        self.held = _inert_windows(layout, weights, tg, len(self.lower))
        if opts.sparse:
            self.held |= (self.theta() == 0) & weight
        if opts.windows is not None:
            self.held |= _outside_windows(layout, weights, opts.windows, len(self.lower))

    def theta(self) -> torch.Tensor:
        """θ (N×D) of the current weights (and freed fields)."""
        theta = self.weights.flat(self.keys)
        if not self.opts.fields:
            return theta
        fields = self.basis.free_vector()[self.free].reshape(1, -1)
        return torch.cat([theta, fields.expand(len(theta), -1)], -1)

    def _fields(self, theta: torch.Tensor) -> torch.Tensor:
        """Every field's free vector (B×M×p) with the freed ones from θ[dw:] (B×…)."""
        full = self.basis.free_vector().expand(len(theta), -1, -1).clone()
        full[:, self.free] = theta.reshape(len(theta), len(self.free), -1)
        return full

    def assign(self, theta: torch.Tensor) -> None:
        """Set the weights (and freed fields) from θ (N×D)."""
        self.weights.set_flat(self.keys, theta[:, :self.dw], list(range(len(theta))))
        if self.opts.fields:
            self.basis.assign_free(self._fields(theta[:1, self.dw:])[0])

    def _basis(self, fields: torch.Tensor):
        """The fields of every member (rows of θ[dw:]) as one group each."""
        eta, raw = self.basis.split_free(self._fields(fields))
        return MotionFields(eta, self.basis.stiffness(raw), self.basis.damping)

    def _run(self, theta, seg: _Segments, rows, copies: int = 1):
        """Residuals (copies × B × R) of the segments, row b of copy c under θ[c, rows[b]]
        (theta: copies × n_m × D); with ``distributed`` the segments dealt to the ranks
        (:func:`~tflearn.parallel.mine`), each simulating its own with all their copies,
        and gathered: where each segment steps on its own (dopri5, or a fixed step), what
        one process gets. Raises SimulationFailed (on every rank, where any rank's fails)."""
        if not self.distributed:
            return self._simulated(theta, seg, rows, copies)
        mine = torch.tensor(parallel.mine(len(seg.motion)), dtype=torch.long)
        part = failed = None
        try:
            if len(mine):
                part = self._simulated(theta, seg.take(mine), rows[mine], copies)
        except SimulationFailed as err:
            failed = (err.reason, err.message)
        got = parallel.all_gather((part, failed))
        for _, failure in got:
            if failure is not None:
                raise SimulationFailed(*failure)
        parts = [(parallel.shard(len(seg.motion), r, len(got)), p) for r, (p, _) in enumerate(got)]
        r = next(p for _, p in parts if p is not None)
        out = r.new_empty(copies, len(seg.motion), r.shape[-1])
        for idx, p in parts:
            if idx:
                out[:, idx] = p
        return out

    def _simulated(self, theta, seg: _Segments, rows, copies: int):
        """:meth:`_run`'s residuals, every segment simulated here."""
        B = len(seg.motion)
        flat = theta[:, rows].reshape(copies * B, -1)
        w = self.weights.with_flat(self.keys, flat[:, :self.dw], seg.motion.repeat(copies))
        basis = self._basis(flat[:, self.dw:]) if self.opts.fields else self.basis
        self.simulations += 1
        q, v = _simulate(self.body, basis, w, seg, self.sim, copies)
        q, v = (x.reshape(copies, B, -1, self.body.nv) for x in (q, v))
        return _residuals(self.body, self.tg, seg, q, v, self.opts.velocity_weight, self.opts.tip_weight)

    def cost(self, theta: torch.Tensor, h: float, motions: list) -> torch.Tensor:
        """Each of ``motions``' multiple-shooting cost Σ r² at horizon h and θ
        (len(motions)×D); ∞ for one whose simulation fails (the batch is then simulated
        motion by motion)."""
        return self.residuals(theta, h, motions)[0]

    def residuals(self, theta: torch.Tensor, h: float, motions: list):
        """(cost (len(motions)), [each motion's residuals (S_j×R), None where its
        simulation fails]) at horizon h and θ (len(motions)×D): :meth:`cost`'s, with the
        residuals of every segment of each motion."""
        seg = segments(self.tg, h, motions)
        rows = _rows(seg, motions)
        try:
            r = self._run(theta[None], seg, rows)[0]
            cost = torch.zeros(len(motions), dtype=r.dtype).index_add_(0, rows, (r ** 2).sum(-1))
            return cost, [r[rows == i] for i in range(len(motions))]
        except SimulationFailed:
            if len(motions) == 1:
                return torch.tensor([math.inf], dtype=torch.float64), [None]
        parts = [self.residuals(theta[i:i + 1], h, [j]) for i, j in enumerate(motions)]
        return torch.cat([p[0] for p in parts]), [p[1][0] for p in parts]

    def jacobian(self, theta: torch.Tensor, h: float, motions: list):
        """[(J (S_j×R×D), r (S_j×R)) of each motion's segments] at θ (n_m×D), J by
        forward differences of d + 1 copies simulated in one batch, d the parameters
        that some motion of the batch does not hold (:attr:`held`; a column held by all
        is 0). Raises SimulationFailed."""
        D = theta.shape[1]
        cols = (~self.held[motions]).any(0).nonzero().flatten()           # d columns differenced
        d = len(cols)
        eps = self.opts.step * theta.abs().clamp_min(1.0)                 # n_m × D
        copies = theta.unsqueeze(0).repeat(d + 1, 1, 1)                   # (d+1) × n_m × D
        copies[torch.arange(1, d + 1), :, cols] += eps[:, cols].T
        seg = segments(self.tg, h, motions)
        rows = _rows(seg, motions)
        r = self._run(copies, seg, rows, d + 1)                           # (d+1) × B × R
        J = r.new_zeros(len(seg.motion), r.shape[-1], D)                  # B × R × D
        J[:, :, cols] = ((r[1:] - r[:1]) / eps[rows][:, cols].T[:, :, None]).permute(1, 2, 0)
        return [(J[rows == i], r[0][rows == i]) for i in range(len(motions))]

    def normal_equations(self, theta: torch.Tensor, h: float, motions: list):
        """(JᵀJ (n_m×D×D), Jᵀr (n_m×D)) of each motion at θ (n_m×D), J from
        :meth:`jacobian`. Raises SimulationFailed."""
        return _normal(self.jacobian(theta, h, motions))


def _inert_windows(layout: list, weights: MotionWeights, tg: Targets, D: int) -> torch.Tensor:
    """(N×D) True for the parameters of θ (``layout``: (key, size) in order) of the windows
    that start at or after their motion's end — placed there by a window rate for motions
    shorter than the longest: their pulses are 0 at every sample, so are their columns."""
    inert = weights.window_onset >= tg.duration[:, None]                  # N×P
    parts = []
    for key, d in layout:
        x = getattr(weights, key)
        if key == "c_raw":
            x = inert[:, None, :].expand(x.shape)
        elif key in ("window_onset", "window_duration"):
            x = inert
        else:
            x = torch.zeros(x.shape, dtype=torch.bool)
        parts.append(x.reshape(weights.N, d))
    parts.append(torch.zeros(weights.N, D - sum(d for _, d in layout), dtype=torch.bool))
    return torch.cat(parts, 1)


def _outside_windows(layout: list, weights: MotionWeights, windows: tuple, D: int) -> torch.Tensor:
    """(N×D) True for every parameter of θ (``layout``: (key, size) in order) but the
    weights c of ``windows``."""
    free = []
    for key, d in layout:
        x = torch.zeros(getattr(weights, key).shape[1:], dtype=torch.bool)
        if key == "c_raw":
            x[:, list(windows)] = True
        free.append(x.reshape(d))
    free = torch.cat(free + [torch.zeros(D - sum(d for _, d in layout), dtype=torch.bool)])
    return (~free).expand(weights.N, -1)


def _normal(linear: list):
    """(JᵀJ (n×D×D), Jᵀr (n×D)) of each motion's [(J (S×R×D), r (S×R))]."""
    rows = torch.cat([torch.full((len(J),), i) for i, (J, _) in enumerate(linear)])
    J, r = (torch.cat(x) for x in zip(*linear))                       # B × R × D, B × R
    D = J.shape[-1]
    JtJ = torch.zeros(len(linear), D, D, dtype=J.dtype).index_add_(0, rows, J.transpose(1, 2) @ J)
    Jtr = torch.zeros(len(linear), D, dtype=J.dtype).index_add_(
        0, rows, (J.transpose(1, 2) @ r[..., None])[..., 0])
    return JtJ, Jtr


def _gain_ratio(J: torch.Tensor, r: torch.Tensor, delta: torch.Tensor, cost: float) -> float:
    """ρ = (‖r‖² − cost) / (‖r‖² − ‖r + J δ‖²): the cost's fall after the step δ over the
    fall its linear model J (S×R×D) predicted from the residuals r (S×R)."""
    before = float((r ** 2).sum())
    predicted = before - float(((r + J @ delta) ** 2).sum())
    return (before - cost) / predicted if predicted > 0 else 0.0


def _broyden(J: torch.Tensor, r: torch.Tensor, r_new: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
    """Broyden's rank-one update of one motion's J (S×R×D) after the step δ (D) took its
    residuals from r to r_new (S×R): J + (Δr − J δ) δᵀ / δᵀδ, the least change of J
    that maps δ to the residuals' change."""
    dd = float(delta @ delta)
    if dd == 0.0:
        return J
    return J + torch.einsum("sr,i->sri", r_new - r - J @ delta, delta / dd)


def _rows(seg: _Segments, motions: list) -> torch.Tensor:
    """Each segment's position in ``motions`` (B)."""
    where = {j: i for i, j in enumerate(motions)}
    return torch.tensor([where[int(j)] for j in seg.motion])


def _lm_step(JtJ, Jtr, mu, theta, lower, held):
    """The projected, damped Gauss–Newton step of each motion (see the module docstring);
    the parameters ``held`` (bools like θ) do not move."""
    free = ~((theta <= lower) & (Jtr > 0)) & ~held                       # held at a bound otherwise
    d = torch.diagonal(JtJ, dim1=-2, dim2=-1)
    scale = torch.maximum(d, 1e-12 * d.amax(-1, keepdim=True).clamp_min(1e-300))
    A = JtJ + torch.diag_embed(mu[:, None] * scale)
    mask = free[:, :, None] & free[:, None, :]
    A = torch.where(mask, A, torch.diag_embed(torch.ones_like(d)))
    delta = -torch.linalg.solve(A, torch.where(free, Jtr, torch.zeros_like(Jtr))[..., None])[..., 0]
    return torch.maximum(theta + torch.where(free, delta, torch.zeros_like(delta)), lower)


def keys_of(options: ShootingOptions) -> tuple:
    """The :class:`~tflearn.model.weights.MotionWeights` arrays that ``options`` fits."""
    return WEIGHTS + (TIMING if options.phases else ())


@torch.no_grad()
def shooting_match(body: Body, basis: FieldBasis, weights: MotionWeights, tg: Targets, *,
                   options: ShootingOptions = ShootingOptions(),
                   sim: SimOptions = SimOptions(rtol=1e-6, atol=1e-8, max_evals=20000),
                   motions: Optional[list] = None,
                   callback: Optional[Callable] = None, distributed: bool = False) -> ShootingResult:
    """Fit every motion's weights (and with ``options.phases`` its timing) to its path,
    the basis fixed — or with ``options.fields`` free (``basis`` is then changed in place;
    with several motions, fitted to all their paths at once) —, by multiple shooting and
    Levenberg–Marquardt (module docstring).
    ``motions``: fit these only (indices; the others are left as they are, and the
    result's rows are these motions'). ``weights`` is changed in place;
    ``callback(horizon, iteration, cost (N))`` is called after each iteration. Returns
    a :class:`ShootingResult`. Whatever ``sim.batch`` says, the copies of a segment are
    stepped together (the differences need one discrete map). ``distributed``: every
    rank of a run (:mod:`tflearn.parallel`) calls this with the same problem, and each
    simulates its share of the segments (:meth:`_Problem._run`)."""
    if motions is not None:
        sub = weights.select_motions(motions)
        result = shooting_match(body, basis, sub, tg.select(motions), options=options, sim=sim,
                                callback=callback, distributed=distributed)
        weights.set_flat(keys_of(options), sub.flat(keys_of(options)), motions)
        return result
    if options.fields and tg.N > 1:
        return _shared(_Problem(body, basis, weights, tg, keys_of(options), options, sim, distributed),
                       callback)
    if options.used and not options.fields:
        return _on_used(body, basis, weights, tg, options, sim, callback, distributed)
    keys = keys_of(options)
    prob = _Problem(body, basis, weights, tg, keys, options, sim, distributed)
    theta = prob.theta()
    start, everyone = theta.clone(), list(range(tg.N))
    longest = float(tg.duration.max())
    before = prob.cost(theta, 2 * longest, everyone)
    mu = torch.full((tg.N,), options.mu, dtype=torch.float64)
    result, active = ShootingResult(loss=[]), [j for j in everyone if math.isfinite(float(before[j]))]
    for j in set(everyone) - set(active):
        result.failures[tg.names[j]] = "cannot be simulated from its starting weights"
    h, after = min(options.horizon, longest), before.clone()
    while active:
        cost = _stage(prob, theta, start, mu, h, active, result, callback)
        if h >= longest:             # the last stage's cost is each motion's path loss
            after[active] = cost[active]
            break
        h = min(2 * h, longest)
    again = [j for j in everyone if math.isfinite(float(before[j])) and j not in active]
    if again:                        # motions that left before the whole-motion stage
        after[again] = prob.cost(theta[again], 2 * longest, again)
    worse = ~(after <= before)                         # never end further from the path
    theta[worse], after[worse] = start[worse], before[worse]
    prob.assign(theta)
    result.loss, result.simulations = after.tolist(), prob.simulations
    return result


def _on_used(body, basis, weights, tg, options, sim, callback, distributed) -> ShootingResult:
    """:func:`shooting_match` of each motion alone on the fields it has a weight on
    (``options.used``); the results joined in motion order (each history row one
    motion's, its cost of length 1)."""
    result, keys, rows = ShootingResult(loss=[]), keys_of(options), weights.used()
    for j in range(tg.N):
        used = rows[j].nonzero().flatten().tolist() or list(range(basis.M))  # no weight: every field
        sub = weights.select_motions([j]).select_fields(used)
        res = shooting_match(body, basis.select(used), sub, tg.select([j]),
                             options=replace(options, used=False), sim=sim, callback=callback,
                             distributed=distributed)
        with torch.no_grad():
            for key in keys:                     # per field, or (windows) per motion
                x = getattr(weights, key)
                if key in MotionWeights.PER_FIELD:
                    x[j, used] = getattr(sub, key)[0]
                else:
                    x[j] = getattr(sub, key)[0]
        result.loss += res.loss
        result.history += res.history
        result.failures.update(res.failures)
        result.simulations += res.simulations
    return result


def _jacobians(prob: _Problem, theta, h, motions: list, result: ShootingResult) -> dict:
    """{motion: (J, r)} (:meth:`_Problem.jacobian`) of ``motions`` at θ; if their batch
    cannot be simulated, motion by motion, and a motion that still cannot is left out,
    its reason in ``result.failures``."""
    if not motions:
        return {}
    try:
        return dict(zip(motions, prob.jacobian(theta[motions], h, motions)))
    except SimulationFailed as err:
        if len(motions) == 1:
            result.failures[prob.tg.names[motions[0]]] = f"Jacobian not simulated: {err}"
            return {}
    out = {}
    for j in motions:
        out.update(_jacobians(prob, theta, h, [j], result))
    return out


_BACK_OFF = (0.5, 0.25, 0.125, 0.0625, 0.0)      # α of θ₀ + α(θ − θ₀), in order


def _back_off(prob: _Problem, theta, start, cost, h, lost: list) -> None:
    """Move each ``lost`` motion, whose segments at horizon h cannot be simulated from its
    θ, back towards its starting θ₀: θ ← θ₀ + α(θ − θ₀) for the first α of 1/2, 1/4, …,
    1/16, 0 at which they can (θ, its cost and ``lost`` are updated in place)."""
    for alpha in _BACK_OFF:
        if not lost:
            return
        trial = start[lost] + alpha * (theta[lost] - start[lost])
        for j, cj, th in zip(list(lost), prob.cost(trial, h, lost).tolist(), trial):
            if math.isfinite(cj):
                theta[j], cost[j] = th, cj
                lost.remove(j)


def _still_going(opts: ShootingOptions, motions: list, old, cost, exact: dict, linear: dict) -> list:
    """The ``motions`` that stay in the stage after an iteration that took their costs
    from ``old`` to ``cost``: those above the floor whose cost fell by more than ``tol``
    relatively, and those whose step was taken from an updated J without such a fall —
    only differences may say that a motion has stopped (their J is dropped from
    ``linear``)."""
    going = []
    for j, o in zip(motions, old.tolist()):
        gained = o - float(cost[j]) > opts.tol * o
        if not (exact[j] or gained):
            linear.pop(j, None)
        if float(cost[j]) > opts.floor and (gained or not exact[j]):
            going.append(j)
    return going


def _stage(prob: _Problem, theta, start, mu, h, active: list, result: ShootingResult, callback):
    """The Levenberg–Marquardt iterations of one horizon on the ``active`` motions
    (θ, μ and ``active`` are updated in place), from θ backed off towards ``start`` for
    the motions whose segments cannot be simulated at it. Returns each motion's cost (N)
    at its final θ (∞ where not active)."""
    tg = prob.tg
    cost = torch.full((tg.N,), math.inf, dtype=torch.float64)
    cost[active] = prob.cost(theta[active], h, active)
    lost = [j for j in active if not math.isfinite(float(cost[j]))]
    _back_off(prob, theta, start, cost, h, lost)
    for j in lost:
        result.failures[tg.names[j]] = f"cannot be simulated at horizon {h:.3g} s"
        active.remove(j)
    todo_stage = [j for j in active if float(cost[j]) > prob.opts.floor]
    linear = {}                                  # motion: (J, r, whether J is differences)
    for it in range(prob.opts.iterations):
        fresh = _jacobians(prob, theta, h, [j for j in todo_stage if j not in linear], result)
        linear.update({j: (J, r, True) for j, (J, r) in fresh.items()})
        todo_stage = [j for j in todo_stage if j in linear]
        if not todo_stage:
            break
        JtJ, Jtr = _normal([linear[j][:2] for j in todo_stage])
        exact = {j: linear[j][2] for j in todo_stage}
        old = cost[todo_stage].clone()
        todo = list(range(len(todo_stage)))
        for _ in range(8):                       # μ × 4 for the motions not yet improved
            idx = [todo_stage[i] for i in todo]
            trial = _lm_step(JtJ[todo], Jtr[todo], mu[idx], theta[idx], prob.lower, prob.held[idx])
            c, rs = prob.residuals(trial, h, idx)
            for i, j, cj, th, rj in zip(list(todo), idx, c.tolist(), trial, rs):
                if cj < float(cost[j]):
                    J, r, _ = linear[j]
                    delta = th - theta[j]
                    if prob.opts.broyden and _gain_ratio(J, r, delta, cj) >= 0.25:
                        linear[j] = (_broyden(J, r, rj, delta), rj, False)
                    else:                        # differences at the new θ
                        del linear[j]
                    theta[j], cost[j], mu[j] = th, cj, mu[j] / 3
                    todo.remove(i)
                elif not exact[j]:               # an updated J failed: differences decide
                    todo.remove(i)
                else:
                    mu[j] *= 4
            if not todo:
                break
        result.history.append({"horizon": h, "cost": cost.tolist()})
        if callback:
            callback(h, it, cost.clone())
        todo_stage = _still_going(prob.opts, todo_stage, old, cost, exact, linear)
    active[:] = [j for j in active if tg.names[j] not in result.failures]
    return cost


def _shared(prob: _Problem, callback) -> ShootingResult:
    """:func:`shooting_match` of several motions with the fields free and shared: one
    Levenberg–Marquardt problem over every motion's θ (module docstring, "Shared
    fields"); each horizon from the θ of the last, backed off towards θ₀ where it
    cannot be simulated. Where a motion cannot be simulated from θ₀ nothing is fitted:
    the losses are those at θ₀ (∞ for it) and it is named in ``failures``."""
    tg, everyone = prob.tg, list(range(prob.tg.N))
    longest, theta = float(tg.duration.max()), prob.theta()
    start, result = theta.clone(), ShootingResult(loss=[])
    before = prob.cost(theta, 2 * longest, everyone)
    if not torch.isfinite(before).all():
        result.failures = {tg.names[j]: "cannot be simulated from its starting weights"
                           for j in everyone if not math.isfinite(float(before[j]))}
        result.loss, result.simulations = before.tolist(), prob.simulations
        return result
    h, mu = min(prob.opts.horizon, longest), prob.opts.mu
    while True:
        theta, cost = _backed_off(prob, theta, start, h)
        if theta is None:
            result.failures["fields"] = f"cannot be simulated at horizon {h:.3g} s"
            theta = start
            break
        theta, mu = _shared_stage(prob, theta, cost, mu, h, result, callback)
        if h >= longest:
            break
        h = min(2 * h, longest)
    after = prob.cost(theta, 2 * longest, everyone)
    if not float(after.sum()) <= float(before.sum()):    # never end further from the paths
        theta, after = start, before
    prob.assign(theta)
    result.loss, result.simulations = after.tolist(), prob.simulations
    return result


def _backed_off(prob: _Problem, theta, start, h) -> tuple:
    """(θ₀ + α(θ − θ₀), each motion's cost there) for the first α of 1, ½, ¼, …, 1/16, 0
    at which every motion's segments at horizon h can be simulated; (None, None) if
    none can."""
    everyone = list(range(prob.tg.N))
    for alpha in (1.0,) + _BACK_OFF:
        trial = start + alpha * (theta - start)
        cost = prob.cost(trial, h, everyone)
        if torch.isfinite(cost).all():
            return trial, cost
    return None, None


def _shared_stage(prob: _Problem, theta, cost, mu: float, h: float, result: ShootingResult, callback):
    """The Levenberg–Marquardt iterations of one horizon on (θ_1, …, θ_N, f) together,
    from θ and each motion's cost there: (θ, μ) at the end; stops when the summed cost
    falls by less than ``tol`` relatively, is below N·``floor``, or no μ lowers it."""
    everyone, N, dw = list(range(prob.tg.N)), prob.tg.N, prob.dw
    for it in range(prob.opts.iterations):
        total = float(cost.sum())
        if total <= N * prob.opts.floor:
            break
        try:
            A, g, x, lower, held = _arrow(*prob.normal_equations(theta, h, everyone), theta, prob.lower,
                                          prob.held, dw)
        except SimulationFailed as err:
            result.failures["fields"] = f"Jacobian not simulated: {err}"
            break
        for _ in range(8):
            mus = torch.tensor([mu], dtype=A.dtype)
            step = _lm_step(A[None], g[None], mus, x[None], lower, held[None])[0]
            trial = torch.cat([step[:N * dw].reshape(N, dw), step[N * dw:].expand(N, -1)], -1)
            c = prob.cost(trial, h, everyone)
            if float(c.sum()) < total:
                theta, cost, mu = trial, c, mu / 3
                break
            mu *= 4
        else:
            break
        result.history.append({"horizon": h, "cost": cost.tolist()})
        if callback:
            callback(h, it, cost.clone())
        if total - float(cost.sum()) <= prob.opts.tol * total:
            break
    return theta, mu


def _arrow(JtJ, Jtr, theta, lower, held, dw: int):
    """The joint normal equations of every motion's weights and the fields they share:
    (A (n×n), Jᵀr (n), x (n), lower bounds (n), held (n)), n = N·dw + p, x = (θ_1[:dw],
    …, θ_N[:dw], f) from each motion's (JᵀJ (N×D×D), Jᵀr (N×D)) over (its weights, f)
    and its held parameters (N×D)."""
    N = len(theta)
    ww = torch.block_diag(*JtJ[:, :dw, :dw])
    wf = JtJ[:, :dw, dw:].reshape(N * dw, -1)
    A = torch.cat([torch.cat([ww, wf], 1), torch.cat([wf.T, JtJ[:, dw:, dw:].sum(0)], 1)], 0)
    g = torch.cat([Jtr[:, :dw].reshape(-1), Jtr[:, dw:].sum(0)])
    x = torch.cat([theta[:, :dw].reshape(-1), theta[0, dw:]])
    return (A, g, x, torch.cat([lower[:dw].repeat(N), lower[dw:]]),
            torch.cat([held[:, :dw].reshape(-1), held[0, dw:]]))
