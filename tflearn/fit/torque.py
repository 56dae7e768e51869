"""Torque matching (thesis eq. 3.10/3.11) and its solvers.

For motion j with inverse-dynamics torques T_j(t) and fields (η_i, K_i) the model torque
is linear in the motion's weights x_j = (a_j, b_j, c_j) ∈ R^{M(2+P)}:

    F_j(t) = Φ_j(t) x_j,
    Φ_j(t) = [ψ_ji(t) χ_i | φ_ji(t) χ_i | φ_jk(t) χ_i (window k of field i)]   (n×M(2+P))

(χ_i = χ_i(ν_j(t), v_j(t)) with the basis' field damping, :class:`~tflearn.model.fields.FieldBasis`;
the window columns field by field, P sub-movement windows, :class:`~tflearn.model.weights.MotionWeights`).

The cost of a motion is relative to its torque energy S_j = Σ_t w_t ‖T_j(t)‖²:

    C_j = Σ_t w_t ‖T_j(t) − F_j(t)‖² / S_j = 1 − 2 h_jᵀ x_j + x_jᵀ G_j x_j,
    G_j = Σ_t w_t Φᵀ Φ / S_j,   h_j = Σ_t w_t Φᵀ T_j / S_j

(w the trapezoid weights, so Σ_t w_t f(t) ≈ ∫ f dt as in eq. 3.9, zero on the few
samples at each end where spline torques are unreliable — see :func:`.targets.prepare`). With the fields fixed
the exact weights solve a batched NNLS (:func:`solve_weights`); the EM alternation
(:func:`em`) repeats that solve and gradient steps on the fields' centres and stiffnesses
(and phases, if variable) with the weights held — by the envelope theorem this is
gradient descent on the reduced cost min_x C(x, η, K). :func:`joint_descent` is the plain
alternative: gradient descent on fields and weights together.
"""
from __future__ import annotations

import math
import warnings
from typing import Callable, Optional

import torch

from .. import parallel
from ..model.fields import FieldBasis
from ..model.weights import MotionWeights, pulse_profile, pulse_slope, step_profile, step_slope
from .nnls import nnls, packed, take, warn_unconverged
from .targets import Targets, chunks


class DivergenceWarning(RuntimeWarning):
    """A fitting step rejected because its cost, loss, gradient or simulation went
    non-finite; the message names the motions."""


def _warn_nonfinite(costs: torch.Tensor, tg: Targets, what: str) -> None:
    bad = [n for n, c in zip(tg.names, costs.tolist()) if not math.isfinite(c)]
    if bad:
        warnings.warn(f"{what}: step rejected: non-finite torque cost for {', '.join(bad)}",
                      DivergenceWarning, stacklevel=3)


def design(basis: FieldBasis, weights: MotionWeights, tg: Targets,
           scale: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Φ (N×T×n×M(2+P)): the torque of unit step, pulse and window weights on each field;
    ``scale`` (N×T×n): s ⊙ Φ instead, folded into the fields' torques before the
    columns are formed."""
    chi = basis(tg.q, tg.v).transpose(-1, -2)                          # N×T×n×M
    if scale is not None:
        chi = scale.unsqueeze(-1) * chi
    return profile_columns(chi, weights, tg.t)


def profile_columns(x: torch.Tensor, weights: MotionWeights, t: torch.Tensor) -> torch.Tensor:
    """x (N×T×…×M, one entry per field at each sample) times each field's time profiles:
    (N×T×…×M(2+P)), the columns of the step weights, the pulse weights and the P window
    weights field by field (:func:`design`'s order), at each motion's times t (N×T)."""
    extra = (1,) * (x.dim() - 3)
    psi, phi = weights.profiles_per_motion(t)                          # N×T×M
    N, T, M = psi.shape
    cols = [psi.view(N, T, *extra, M) * x, phi.view(N, T, *extra, M) * x]
    if weights.P:
        win = weights.windows_per_motion(t)                            # N×T×P
        cols.append((x.unsqueeze(-1) * win.view(N, T, *extra, 1, -1)).flatten(-2))
    return torch.cat(cols, dim=-1)


def residual_scale(tg: Targets) -> torch.Tensor:
    """s = √(w ω / S) (N×T×n): the factor that makes Σ (s ⊙ (T − F))² the relative cost C_j."""
    return tg.weigh((tg.wt / tg.torque_scale()[:, None]).sqrt()[..., None].expand(tg.tau.shape))


def scaled_design(basis: FieldBasis, weights: MotionWeights, tg: Targets,
                  scale: Optional[torch.Tensor] = None) -> torch.Tensor:
    """s ⊙ Φ per motion (N × Tn × X), ``scale`` s (:func:`residual_scale`, computed when
    not given): C_j = ‖s ⊙ T_j − Φ̃_j x_j‖² with Φ̃ this."""
    N, T, n = tg.tau.shape
    s = residual_scale(tg) if scale is None else scale
    return design(basis, weights, tg, s).reshape(N, T * n, -1)


def normal_equations(basis: FieldBasis, weights: MotionWeights, tg: Targets):
    """(G (N×X×X), h (N×X)) of the relative torque cost, X = M(2+P): G = Φ̃ᵀΦ̃ and
    h = Φ̃ᵀ(s ⊙ T) with Φ̃ = :func:`scaled_design`, one batched product per motion."""
    s = residual_scale(tg)
    Phi = scaled_design(basis, weights, tg, s)
    h = (Phi.transpose(-1, -2) @ (s * tg.tau).reshape(tg.N, -1, 1)).squeeze(-1)
    return Phi.transpose(-1, -2) @ Phi, h


@torch.no_grad()
def solve_weights(basis: FieldBasis, weights: MotionWeights, tg: Targets,
                  support: Optional[torch.Tensor] = None, ridge: float = 0.0) -> torch.Tensor:
    """Set every motion's (a, b, c) to its exact NNLS optimum; returns the costs C_j (N).

    ``support`` (N×M(2+P) bool, [a | b | c]) restricts the optimum to those weights, the others
    held at 0 (their rows of the normal equations become x_i = 0 with a negative
    gradient, so Lawson–Hanson never frees them). ``ridge`` λ ≥ 0 minimises
    C_j + λ ḡ_j ‖x_j‖² instead (ḡ_j the mean of diag G_j): nearly collinear fields can no
    longer cancel each other with huge weights, which make a stiff program an explicit
    solver cannot step (the returned costs are still C_j). Many motions are solved a
    chunk at a time (:func:`~.targets.chunks`)."""
    parts = chunks(tg, weights.a_raw.shape[1] * (2 + weights.P))
    if len(parts) == 1:
        return _solve_weights(basis, weights, tg, support, ridge)
    costs, keys = torch.empty(tg.N, dtype=torch.float64), ("a_raw", "b_raw", "c_raw")
    for idx in parts:
        sub = weights.select_motions(idx)
        costs[idx] = _solve_weights(basis, sub, tg.select(idx, trim=True),
                                    None if support is None else support[idx], ridge)
        weights.set_flat(keys, sub.flat(keys), idx)
    return costs


def _solve_weights(basis, weights, tg, support, ridge):
    if support is not None and len(fields := _fields_used(support, basis.M)) < basis.M:
        return _solve_on(fields, basis, weights, tg, support, ridge)
    G, h = normal_equations(basis, weights, tg)
    A = with_ridge(G, ridge)
    if support is None:
        sol = nnls(A, h)
        x = sol.x
    else:
        A, hs, cols, pad = _on_support(A, h, support)
        sol = nnls(A, hs)
        x = torch.zeros_like(h).scatter_(-1, cols, torch.where(pad, 0.0, sol.x))
    warn_unconverged(sol, tg.names, "solve_weights")
    weights.set_vector(x)
    return quadratic_cost(G, h, x)


def quadratic_cost(G: torch.Tensor, h: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """C = 1 − 2 hᵀx + xᵀG x (...) of weights x (...×X) on normal equations G (...×X×X),
    h (...×X): the relative torque cost of x."""
    return 1 - 2 * (h * x).sum(-1) + (x.unsqueeze(-2) @ G @ x.unsqueeze(-1))[..., 0, 0]


def _on_support(G: torch.Tensor, h: torch.Tensor, support: torch.Tensor) -> tuple:
    """Each motion's normal equations (G N×k×k, h N×k) on its ``support`` (N×k bools)
    only, packed in front (:func:`~.nnls.packed`): (G N×W×W, h N×W, the columns N×W,
    padding N×W), W the most any motion supports. A padding row reads x_i = 0 with a
    negative gradient, so that Lawson–Hanson never frees it: each motion's solve costs
    O(W³), not O(k³), where motions of a chunk hold different fields (their union k)."""
    cols, pad = packed(support)
    A, hs = take(G, h, cols, pad)
    return A + torch.diag_embed(pad.to(G.dtype)), torch.where(pad, -1.0, hs), cols, pad


def _solve_on(fields: list, basis, weights, tg, support, ridge):
    """:func:`_solve_weights` with the design of ``fields`` only, those that some motion's
    ``support`` holds: the other fields' weights are 0 either way, and a motion's normal
    equations over every field cost O(M²) where its own few fields cost O(1) (many
    motions pooled with :attr:`~tflearn.config.PoolSection.sharing` own)."""
    cols = columns(fields, basis.M, weights.P)
    sub = weights.select_fields(fields)
    costs = _solve_weights(basis.select(fields), sub, tg, support[:, cols], ridge)
    x = torch.zeros_like(weights.vector())
    x[:, cols] = sub.vector()
    weights.set_vector(x)
    return costs


def columns(fields: list, M: int, P: int) -> torch.Tensor:
    """The columns of ``fields``' weights in the layout of :meth:`MotionWeights.vector`
    (a, b, then c field by field), in the order of ``fields``."""
    i = torch.as_tensor(fields, dtype=torch.long)
    return torch.cat([i, M + i, 2 * M + (P * i[:, None] + torch.arange(P)).flatten()])


def with_ridge(G: torch.Tensor, ridge: float) -> torch.Tensor:
    """G + λ ḡ I (…×X×X), ḡ the mean of G's diagonal; G itself when λ = 0."""
    if not ridge:
        return G
    d = torch.diagonal(G, dim1=-2, dim2=-1)
    return G + torch.diag_embed((ridge * d.mean(-1, keepdim=True)).expand_as(d))


def torque_cost(basis: FieldBasis, weights: MotionWeights, tg: Targets) -> torch.Tensor:
    """C_j (N), differentiable in the fields and the weights (eq. 3.10, relative)."""
    F = (design(basis, weights, tg) @ weights.vector().unsqueeze(1).unsqueeze(-1)).squeeze(-1)
    r = (tg.weigh(tg.tau - F) ** 2).sum(-1)
    return (tg.wt * r).sum(-1) / tg.torque_scale()


def by_chunks(f, basis: FieldBasis, weights: MotionWeights, tg: Targets) -> torch.Tensor:
    """``f(basis, weights, targets)``, a per-motion quantity (N×…), evaluated a chunk of
    motions at a time (:func:`~.targets.chunks`; one chunk: the whole ``weights`` and
    ``tg``), so that no design matrix of every motion is built at once. No gradient."""
    parts = chunks(tg, weights.a_raw.shape[1] * (2 + weights.P))
    with torch.no_grad():
        if len(parts) == 1:
            return f(basis, weights, tg)
        rows = [f(basis, weights.select_motions(i), tg.select(i, trim=True)) for i in parts]
        out = rows[0].new_empty((tg.N,) + rows[0].shape[1:])
        for i, x in zip(parts, rows):
            out[i] = x
        return out


def torque_costs(basis: FieldBasis, weights: MotionWeights, tg: Targets) -> torch.Tensor:
    """C_j (N), no gradient: :func:`torque_cost` a chunk of motions at a time
    (:func:`by_chunks`), each chunk's design built for the fields its motions have a
    weight on only (the others' torques are multiplied by 0): O(fields used), not O(M),
    for many motions on fields of their own."""
    return by_chunks(_cost_on_used, basis, weights, tg)


def _cost_on_used(basis, weights, tg):
    fields = _fields_used(weights.vector().detach(), basis.M)
    if len(fields) == basis.M:
        return torque_cost(basis, weights, tg)
    return torque_cost(basis.select(fields), weights.select_fields(fields), tg)


def relative_rms_torque_error(basis, weights, tg: Targets) -> torch.Tensor:
    """sqrt(C_j): RMS torque error relative to the RMS torque, per motion (N)."""
    return torque_costs(basis, weights, tg).clamp_min(0).sqrt()


def field_parameters(basis: FieldBasis, weights: MotionWeights, phases: bool) -> list:
    params = [basis.eta, *basis.stiffness.parameters()]
    return params + (weights.phase_parameters() if phases else [])


PHASES = ("step_onset", "step_duration", "pulse_onset", "pulse_duration")


class _FieldParameters:
    """The fields' free parameters as one vector θ laid out field by field:
    θ_i = [η_i (n), the stiffness entries its kind leaves free (not the structural zeros
    of diag/block kinds), and with ``phases`` the N onsets/durations of each profile].
    Each field's torque depends on θ_i alone, so ∂r/∂θ is assembled block by block."""

    def __init__(self, basis: FieldBasis, weights: MotionWeights, tg: Targets, phases: bool):
        self.basis, self.weights, self.tg, self.phases = basis, weights, tg, phases
        self.M, self.n = basis.eta.shape
        self.N = weights.N
        self.flat_mask = basis.free_stiffness
        self.s = basis.free_size - self.n
        self.p = basis.free_size + (4 * self.N if phases else 0)
        self.scale = residual_scale(tg)
        self.windows = weights.windows_per_motion(tg.t).detach()          # N×T×P

    def vector(self) -> torch.Tensor:
        blocks = [self.basis.free_vector()]
        if self.phases:
            blocks += [getattr(self.weights, k).detach().T for k in PHASES]
        return torch.cat(blocks, dim=-1).reshape(-1)

    def _split(self, th: torch.Tensor):
        """θ (...×p) → η (...×n), raw (scalar: ...; else ...×n×n), phases dict or None."""
        q = self.n + self.s
        eta, raw = self.basis.split_free(th[..., :q])
        ph = None
        if self.phases:
            ph = dict(zip(PHASES, th[..., q:].reshape(th.shape[:-1] + (4, self.N)).unbind(-2)))
        return eta, raw, ph

    @torch.no_grad()
    def assign(self, theta: torch.Tensor) -> None:
        th = theta.reshape(self.M, self.p)
        self.basis.assign_free(th[:, :self.n + self.s])
        _, _, ph = self._split(th)
        if ph is not None:
            for k in PHASES:
                getattr(self.weights, k).copy_(ph[k].T)
        self.weights.project_()

    def residual(self, Phi: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """r = s ⊙ (T − Φ x) per motion (N × Tn), Φ scaled by this ``scale`` (:func:`scaled_design`)."""
        return (self.scale * self.tg.tau).reshape(self.N, -1) - (Phi @ x.unsqueeze(-1)).squeeze(-1)

    def field_term(self, i: int, th: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """Field i's part of the weighted residual, −√(w/S)(a ψ + b φ) χ_i (R), as a
        function of θ_i (the definition :meth:`field_jacobian`'s closed form is checked
        against by forward-mode autodiff)."""
        from torch.func import functional_call
        eta, raw, ph = self._split(th)
        chi = functional_call(self.basis, {"eta": eta[None], "stiffness.raw": raw[None]},
                              (self.tg.q, self.tg.v))[..., 0, :]
        act, _ = self._activation(i, ph, x, slopes=False)
        return (-self.scale * act.unsqueeze(-1) * chi).reshape(-1)

    def jacobian(self, theta, x, fields: Optional[list] = None) -> torch.Tensor:
        """∂r/∂θ (R × Mp), field by field (:meth:`field_jacobian`); ``fields``: the
        columns of these fields only (R × len(fields)·p)."""
        th = theta.reshape(self.M, self.p)
        fields = range(self.M) if fields is None else fields
        J = torch.empty(self.tg.tau.shape + (len(fields), self.p), dtype=theta.dtype)
        for col, i in enumerate(fields):
            self.field_jacobian(i, th[i], x, J[..., col, :])
        return J.reshape(-1, len(fields) * self.p)

    def active(self, x) -> list:
        """The fields some motion has a weight on (a, b or c of ``x`` > 0): the others'
        columns of ∂r/∂θ are zero, their torque being multiplied by zero."""
        return _fields_used(x, self.M)

    def field_jacobian(self, i: int, th: torch.Tensor, x: torch.Tensor, out: torch.Tensor) -> None:
        """∂(:meth:`field_term`)/∂θ_i in closed form, written into ``out`` (N×T×n×p, a
        view of the whole Jacobian). With d = ν − η_i,
        u = d + ζ v, g = exp(−½ dᵀK d) and χ = −K u g:

            ∂χ/∂η = g (K − (K u)(K d)ᵀ),
            ∂χ[ΔK] = g (½ (K u)(dᵀ ΔK d) − ΔK u),

        with ΔK = K Δκ (scalar, K = e^κ I) or ΔK = ΔL Lᵀ + L ΔLᵀ for the free entry
        (a, b) of L (ΔL = e_a e_bᵀ, times L_aa on the diagonal, whose parameter is
        log L_aa); the phases enter through the activation only, ∂ψ(s)/∂onset =
        −ψ'(s)/λ and ∂ψ(s)/∂λ = −ψ'(s) s/λ for s = (t − onset)/λ."""
        eta, raw, ph = self._split(th)
        q, v, n = self.tg.q, self.tg.v, self.n
        d = q - eta
        u = d + self.basis.damping * v if self.basis.damping else d
        if self.flat_mask is None:
            K = self.basis.stiffness(raw)
        else:
            L = self.basis.stiffness.factor(raw)
            K = L @ L.T
        Kd, Ku = d @ K, u @ K                                       # K symmetric
        dKd = (d * Kd).sum(-1, keepdim=True)
        g = torch.exp(-0.5 * dKd)                                   # N×T×1
        act, dact = self._activation(i, ph, x)
        rows = g * (-self.scale * act.unsqueeze(-1))                # N×T×n: −√(w/S) act g
        e, s = out[..., :n], out[..., n:n + self.s]
        torch.mul(Ku[..., :, None], Kd[..., None, :], out=e)
        torch.sub(K, e, out=e).mul_(rows[..., None])
        if self.flat_mask is None:
            torch.mul(Ku * (0.5 * dKd - 1), rows, out=s[..., 0])
        else:
            a, b = self.flat_mask // n, self.flat_mask % n
            c = torch.where(a == b, L[a, a], torch.ones_like(L[a, a]))
            w, z = u @ L, d @ L                                     # Lᵀu, Lᵀd
            dK_u = (torch.eye(n, dtype=th.dtype)[:, a] * w[..., None, b]
                    + L[:, b] * u[..., None, a])                    # ΔK u, N×T×n×s
            torch.mul(Ku[..., :, None] * (d[..., a] * z[..., b])[..., None, :] - dK_u,
                      c * rows[..., None], out=s)
        if dact is not None:                                        # N×T×4×N, motion j's own
            chi = -Ku * g
            torch.mul(-self.scale[..., None, None] * chi[..., None, None], dact[:, :, None],
                      out=out[..., n + self.s:].unflatten(-1, (4, self.N)))

    def _activation(self, i: int, ph, x, slopes: bool = True):
        """Field i's activation (N×T) and, with variable phases (``ph`` given) and
        ``slopes``, its derivatives by each motion's phases (N×T×4×N in PHASES order;
        only column j of motion j is non-zero), else None."""
        own = ph is not None and slopes
        if ph is None:
            ph = {k: getattr(self.weights, k)[:, i].detach() for k in PHASES}
        t, M, P = self.tg.t, self.M, self.weights.P
        act, grads = 0.0, []
        for weight, profile, slope, on, dur in (
                (x[:, i, None], step_profile, step_slope, "step_onset", "step_duration"),
                (x[:, M + i, None], pulse_profile, pulse_slope, "pulse_onset", "pulse_duration")):
            lam = ph[dur][:, None]
            s = (t - ph[on][:, None]) / lam
            act = act + weight * profile(s)
            if own:
                ds = weight * slope(s) / lam
                grads += [-ds, -ds * s]
        if P:                                     # the windows' timing is not among θ
            c = x[:, 2 * M + i * P:2 * M + (i + 1) * P]
            act = act + (self.windows * c[:, None]).sum(-1)
        if not own:
            return act, None
        eye = torch.eye(self.N, dtype=act.dtype)
        return act, torch.stack(grads, dim=-1)[..., None] * eye[:, None, None, :]


def _used(x: torch.Tensor, M: int) -> torch.Tensor:
    """Which of M fields each motion has a weight on (N×M bools) in weights x (N×M(2+P),
    the layout of :meth:`MotionWeights.vector`)."""
    return (x[:, :M] > 0) | (x[:, M:2 * M] > 0) | (x[:, 2 * M:].reshape(len(x), M, -1) > 0).any(-1)


def _fields_used(x: torch.Tensor, M: int) -> list:
    """The fields (indices, ascending) on which some motion has a weight in ``x``
    (N×M(2+P), :func:`_used`; weights > 0, or a support's True)."""
    return _used(x, M).any(0).nonzero().flatten().tolist()


def _projected_normal(J, Phi, r, x):
    """The Gauss–Newton terms (JₚᵀJₚ, Jₚᵀr) of Kaufman's variable-projection Jacobian
    Jₚ = J − Φ_a (Φ_aᵀΦ_a)⁻¹ Φ_aᵀ J per motion, Φ_a the scaled design columns of the
    weights that are active (x > 0): the step then accounts for the weights re-solving
    themselves instead of holding them fixed. Jₚ is formed (in J's storage) rather than
    expanded as JᵀJ − Bᵀ(Φ_aᵀΦ_a)⁻¹B: where the active columns nearly span a field's
    derivative that difference cancels (0.6% of JₚᵀJₚ's largest entry lost on 100 random
    programs at the library's fields).

    J (N × Tn × p, overwritten), Φ (N × Tn × X), r (N × Tn), x (N × X) → (p × p, p)."""
    active = (x > 0).to(Phi.dtype)                                   # N×X
    Phi = Phi * active[:, None, :]
    G = Phi.transpose(-1, -2) @ Phi
    G = G + torch.diag_embed(1 - active) + 1e-12 * torch.diag_embed(
        torch.diagonal(G, dim1=-2, dim2=-1).amax(-1, keepdim=True).expand_as(active))
    coef = torch.linalg.solve(G, Phi.transpose(-1, -2) @ J)
    Jp = torch.baddbmm(J, Phi, coef, alpha=-1, out=J).reshape(-1, J.shape[-1])
    return Jp.T @ Jp, Jp.T @ r.reshape(-1)


class _Motions:
    """The motions of :func:`em`, cut into chunks (:func:`~.targets.chunks`; one chunk
    with ``phases``, whose θ holds every motion's phases), each chunk's Jacobian built,
    projected and summed before the next, so that memory stays bounded however many
    motions there are; the motions that use the same fields at their first NNLS weights
    go together, so that a chunk's Jacobian has the columns of few fields (:meth:`normal`).

    ``shared`` (a run of many processes, :mod:`tflearn.parallel`) with at least as many
    chunks as ranks: chunk c is rank c mod size's (:func:`~tflearn.parallel.shard`),
    which solves its weights and forms its terms of JᵀJ and Jᵀr; the costs, terms and
    weights are gathered, and every rank adds the terms in chunk order, as one process
    does. The chunks are those one process cuts, so a run's steps are a single process'
    to the last bit, whatever its number of processes (an all-reduce of each rank's
    partial sums would group the additions by rank). With fewer chunks every rank does
    the whole work itself: one process forms a chunk's JᵀJ as one product over all its
    motions' rows, which no split between ranks reproduces."""

    def __init__(self, basis: FieldBasis, weights: MotionWeights, tg: Targets, support, shared: bool,
                 phases: bool):
        self.all, self.N = weights, tg.N
        width = basis.M * (basis.free_size + 2 + weights.P)
        parts = [list(range(tg.N))] if phases else chunks(tg, width)
        if len(parts) > 1:
            parts = chunks(tg, width, self._uses(basis, weights, tg, support))
        self.chunks, self.shared = parts, shared and 1 < parallel.size() <= len(parts)
        whole = len(parts) == 1
        self.parts = [parts[c] for c in parallel.mine(len(parts))] if self.shared else parts
        self.weights = [weights] if whole else [weights.select_motions(p) for p in self.parts]
        tgs = [tg] if whole else [tg.select(p, trim=True) for p in self.parts]
        self.support = [support if whole or support is None else support[p] for p in self.parts]
        self.fps = [_FieldParameters(basis, w, t, phases) for w, t in zip(self.weights, tgs)]

    @staticmethod
    def _uses(basis, weights, tg, support) -> list:
        """The fields (a tuple) each motion has a weight on at its NNLS optimum."""
        w = weights.select_motions(list(range(tg.N)))
        solve_weights(basis, w, tg, support)
        return [tuple(row.nonzero().flatten().tolist()) for row in _used(w.vector().detach(), basis.M)]

    def vector(self) -> torch.Tensor:
        return self.fps[0].vector()

    def assign(self, theta: torch.Tensor) -> None:
        for fp in self.fps:
            fp.assign(theta)

    def _gather(self, rows: torch.Tensor) -> torch.Tensor:
        """``rows`` (N×…, this rank's chunks' rows filled) with every chunk's rows, from
        the rank that holds it."""
        got = parallel.gather_motions(len(self.chunks), [rows[p] for p in self.parts])
        for part, r in zip(self.chunks, got):
            rows[part] = r
        return rows

    def solve(self, basis: FieldBasis) -> torch.Tensor:
        """C_j (N) of every motion at its NNLS weights."""
        costs = torch.empty(self.N, dtype=torch.float64)
        for fp, support, part in zip(self.fps, self.support, self.parts):
            costs[part] = solve_weights(basis, fp.weights, fp.tg, support)
        return self._gather(costs) if self.shared else costs

    @staticmethod
    def _term(fp: _FieldParameters, theta: torch.Tensor):
        """(fields, JᵀJ, Jᵀr) of one chunk (:func:`_projected_normal`) on the columns of the
        fields it uses only (:meth:`_FieldParameters.active`), of the Jacobian and of the
        design, the rest being zero or multiplied by zero weights; None if it uses none."""
        x = fp.weights.vector().detach()
        fields = fp.active(x)
        if not fields:
            return None
        own = fp.weights.select_fields(fields)                      # every weight > 0 is here
        Phi = scaled_design(fp.basis.select(fields), own, fp.tg, fp.scale)
        x_f = own.vector().detach()
        J = fp.jacobian(theta, x, fields).reshape(Phi.shape[:2] + (-1,))
        return (fields, *_projected_normal(J, Phi, fp.residual(Phi, x_f), x_f))

    @torch.no_grad()
    def normal(self, theta: torch.Tensor):
        """(JᵀJ, Jᵀr) of every motion, the chunks' terms (:meth:`_term`) added in chunk order."""
        terms = [self._term(fp, theta) for fp in self.fps]
        if self.shared:
            terms = parallel.gather_motions(len(self.chunks), terms)
        n, p = theta.numel(), self.fps[0].p
        A, g = theta.new_zeros(n, n), theta.new_zeros(n)
        for term in terms:
            if term is None:
                continue
            fields, a, b = term
            if len(fields) * p == n:
                A, g = A + a, g + b
                continue
            cols = (torch.tensor(fields)[:, None] * p + torch.arange(p)).flatten()
            A[cols[:, None], cols] += a
            g[cols] += b
        return A, g

    def finish(self) -> None:
        """Every motion's weights into the caller's ``weights``."""
        if self.weights[0] is self.all:
            return
        rows = torch.empty(self.N, self.weights[0].vector().shape[1], dtype=torch.float64)
        for w, part in zip(self.weights, self.parts):
            rows[part] = w.vector().detach()
        self.all.set_vector(self._gather(rows) if self.shared else rows)


def em(basis: FieldBasis, weights: MotionWeights, tg: Targets, steps: int = 50,
       phases: bool = False, tol: float = 1e-10, callback: Optional[Callable] = None,
       support: Optional[torch.Tensor] = None, distributed: bool = False,
       max_step: Optional[float] = None, min_gain: float = 0.0) -> list:
    """EM-style alternation: exact NNLS weights, then a damped Gauss–Newton step on the
    fields' centres and stiffnesses (and phases) with those weights held.

    With x* the NNLS weights, the residual r(θ) = √(w/S)(T − Φ(θ) x*) is linearised,
    J = ∂r/∂θ (in closed form, :meth:`_FieldParameters.field_jacobian`), and the Levenberg–Marquardt step
        (JᵀJ + μ diag(JᵀJ)) δ = −Jᵀ r
    is accepted when the reduced cost min_x C(x, θ + δ) (weights re-solved) decreases,
    μ shrinking on success and growing on failure. J is Kaufman's variable-projection
    Jacobian (:func:`_projected_normal`): the part of ∂r/∂θ that the active weights
    cannot absorb, so the step follows the reduced cost along the long curved valleys
    (centre distance, stiffness and weights trade off far from a centre) that
    first-order descent crawls along. Stops after ``steps`` accepted or rejected
    steps, or when the cost falls by less than ``tol`` (relative) or by less than ``min_gain``
    per motion (absolute: N·min_gain on the sum, so the rule does not tighten as motions are
    added, as ``tol`` on a sum of N costs does). ``callback(step, costs)``
    is called every step. ``support`` restricts the weights (see :func:`solve_weights`).
    ``max_step``: a trust region in θ's own units (centres in rad, stiffness as log of
    the factor's diagonal): μ grows until every |δθ_k| ≤ max_step. Marquardt's scaling
    makes the step scale-free, so a field whose weights are small gets a full-size
    step from a tiny gradient; without a bound one step can throw it to ETA_MAX and
    K_RANGE, where its NNLS weight is 0 and it never returns (None: no bound).
    Returns the cost history (sum over motions) and leaves the weights at their NNLS
    optimum.

    ``distributed``: in a run of many processes the ranks share the chunks of motions,
    each solving its chunks' weights and forming their terms of JᵀJ and Jᵀr, added in
    chunk order on every rank (:class:`_Motions`), so every rank takes one process' steps
    (not with variable ``phases``, whose θ holds every motion's phases, nor with fewer
    chunks than ranks: then every rank runs it whole)."""
    own = _Motions(basis, weights, tg, support, distributed and not phases, phases)
    theta = own.vector()
    costs = own.solve(basis)
    history = [float(costs.sum())]
    mu = 1e-3
    for step in range(steps):
        A, g = own.normal(theta)
        d = torch.diagonal(A).clone()
        d = d + 1e-12 * d.max().clamp_min(1e-300)
        accepted = False
        for _ in range(8):
            delta = torch.linalg.solve(A + mu * torch.diag(d), -g)
            while max_step is not None and float(delta.abs().max()) > max_step:
                mu *= 4                                      # a trust region in θ's units
                delta = torch.linalg.solve(A + mu * torch.diag(d), -g)
            own.assign(theta + delta)
            new_costs = own.solve(basis)
            _warn_nonfinite(new_costs, tg, "EM")
            if float(new_costs.sum()) < history[-1]:         # False for NaN: rejected
                theta = own.vector()
                costs, accepted, mu = new_costs, True, max(mu / 3, 1e-9)
                break
            mu *= 4
        if not accepted:
            own.assign(theta)
            costs = own.solve(basis)
            break
        gain = history[-1] - float(costs.sum())
        history.append(float(costs.sum()))
        if callback:
            callback(step, costs.detach())
        if gain <= tol * max(history[-2], 1e-300) or gain <= min_gain * own.N:
            break
    own.finish()
    return history


def joint_descent(basis: FieldBasis, weights: MotionWeights, tg: Targets, steps: int = 100,
                  lr: float = 0.03, phases: bool = False,
                  callback: Optional[Callable] = None) -> list:
    """Plain projected gradient descent (Adam) on fields and weights together."""
    params = field_parameters(basis, weights, phases) + [weights.a_raw, weights.b_raw, weights.c_raw]
    opt = torch.optim.Adam(params, lr=lr)
    history = []
    for step in range(steps):
        opt.zero_grad()
        costs = torque_cost(basis, weights, tg)
        loss = costs.sum()
        loss.backward()
        opt.step()
        basis.project_()
        weights.project_()
        history.append(float(loss.detach()))
        if callback:
            callback(step, costs.detach())
    with torch.no_grad():
        history.append(float(torque_cost(basis, weights, tg).sum()))
    return history
