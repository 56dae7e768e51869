"""Global search for a basis: data-driven centres, batched multi-start, greedy growth.

The thesis found local descent fails from poor guesses (§4.1, §4.4). tflearn needs no
guess: fields are added one at a time (matching pursuit over torque residuals),

1. candidate centres come from the data — each motion's *torque-line centre* (a field
   with isotropic K pushes along η − ν, so the lines ν_t + s·r_t through the samples along
   the residual torques r_t meet at η; least squares gives
   (Σ w_t P_t + εI) η = Σ w_t P_t ν_t + ε ν_end, P_t = I − r̂_t r̂_tᵀ, w_t = ‖r_t‖² Δt,
   over the whole motion and over each half), the postures it settles at and passes
   through, points beyond them along the residual torque, and seeded random
   perturbations of all of these;
2. each candidate is scored with every stiffness of a coarse-to-fine grid by the exact
   NNLS torque cost of the enlarged basis (no simulation), all candidates in one batch;
3. the best joins the basis and EM refines all fields together (:func:`~.torque.em`);
   for a second field, the best pairs of candidates found together
   (:func:`best_pairs`) are refined too, and the best of these starts is kept.

:func:`grow` runs this loop for a set of motions, :func:`pool` joins per-motion fits
into one basis, :func:`merge_close` merges fields whose centres and stiffnesses nearly
coincide, and :func:`field_shares` ranks fields for backward elimination.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import torch

from ..model.fields import FieldBasis
from ..model.weights import MotionWeights, step_profile
from .nnls import nnls
from .targets import Targets
from .torque import DivergenceWarning, by_chunks, design, normal_equations, quadratic_cost


def residual_torques(basis: FieldBasis, weights: MotionWeights, tg: Targets) -> torch.Tensor:
    """T_j(t) − F_j(t) (N×T×n) at the current weights."""
    with torch.no_grad():
        if basis.M == 0:
            return tg.tau.clone()
        x = weights.vector()
        return tg.tau - (design(basis, weights, tg) @ x[:, None, :, None]).squeeze(-1)


def torque_line_centre(q: torch.Tensor, r: torch.Tensor, w: torch.Tensor,
                       anchor: torch.Tensor, eps: float = 1e-3) -> torch.Tensor:
    """Least-squares meeting point of the lines {q_t + s r_t}; q, r (T×n), w (T) → (n).

    Solves (Σ w_t P_t + ε S I) η = Σ w_t P_t q_t + ε S anchor, P_t = I − r̂ r̂ᵀ,
    w_t ← w_t ‖r_t‖², S = Σ w_t (the ridge fixes directions the lines leave free)."""
    n = q.shape[-1]
    norm = r.norm(dim=-1, keepdim=True)
    u = r / norm.clamp_min(1e-12)
    wt = w * norm.squeeze(-1) ** 2
    P = torch.eye(n, dtype=q.dtype) - u.unsqueeze(-1) * u.unsqueeze(-2)
    S = wt.sum().clamp_min(1e-12)
    A = (wt[:, None, None] * P).sum(0) + eps * S * torch.eye(n, dtype=q.dtype)
    b = (wt[:, None, None] * P @ q.unsqueeze(-1)).squeeze(-1).sum(0) + eps * S * anchor
    return torch.linalg.solve(A, b)


def candidate_centres(tg: Targets, residual: torch.Tensor, count: int,
                      generator: torch.Generator) -> torch.Tensor:
    """Data-driven candidate centres (count×n), see the module docstring."""
    cands = []
    for j in range(tg.N):
        m = tg.mask[j]
        q, r, w = tg.q[j][m], residual[j][m], tg.wt[j][m]
        T = q.shape[0]
        q_end = q[-1]
        for lo, hi in ((0, T), (0, T // 2), (T // 2, T)):
            cands.append(torque_line_centre(q[lo:hi], r[lo:hi], w[lo:hi], q[min(hi, T) - 1]))
        mag = r.norm(dim=-1)
        late = r[T // 2:].mean(0)
        late_dir = late / late.norm().clamp_min(1e-12)
        k = int(mag.argmax())
        peak_dir = r[k] / mag[k].clamp_min(1e-12)
        for s in (0.0, 0.3, 0.7):
            cands.append(q_end + s * late_dir)
            cands.append(q[k] + (s + 0.3) * peak_dir)
        cands.append(q[T // 2])
    base = torch.stack(cands)
    extra = max(count - base.shape[0], 0)
    if extra:
        cpu = {"generator": generator, "device": "cpu"}     # the same draws on every device
        pick = torch.randint(0, base.shape[0], (extra,), **cpu)
        noise = 0.3 * torch.randn(extra, base.shape[1], dtype=base.dtype, **cpu)
        base = torch.cat([base, base[pick] + noise.to(base.device)])
    return base


@torch.no_grad()
def score_candidates(basis: FieldBasis, weights: MotionWeights, tg: Targets,
                     centres: torch.Tensor, stiffnesses) -> torch.Tensor:
    """Summed NNLS torque cost of the basis plus each candidate field (C×S), each an
    isotropic field (K = k I, k from ``stiffnesses``) with the basis' damping ratio, the
    default step and pulse, and a weight on each of the motions' windows.

    The candidates' normal equations share the existing fields' block:
    G = [[G_oo, G_on], [G_noᵀ, G_nn]], h = [h_o, h_n]; all C·S are solved in one
    batched NNLS."""
    M = basis.M
    ks = torch.as_tensor(stiffnesses, dtype=torch.float64)
    u = (tg.t / tg.duration[:, None]).clamp(0, 1)
    psi = step_profile(u)                                                  # N×T
    phi = 0.5 * (1 - torch.cos(2 * torch.pi * u))
    d = tg.q.unsqueeze(0) - centres[:, None, None, :]                      # C×N×T×n
    sq = (d ** 2).sum(-1)
    chi = -(ks[:, None, None, None, None] * (d + basis.damping * tg.v).unsqueeze(0)) * \
        torch.exp(-0.5 * ks[:, None, None, None] * sq.unsqueeze(0)).unsqueeze(-1)  # S×C×N×T×n
    profiles = torch.cat([torch.stack([psi, phi], -1),
                          weights.windows_per_motion(tg.t).detach()], -1)   # N×T×(2+P)
    new = chi.unsqueeze(-1) * profiles[:, :, None]                           # S×C×N×T×n×(2+P)
    ws = tg.wt / tg.torque_scale()[:, None]                                  # N×T
    if tg.coord_weight is not None:                                          # N×T×n: ω_k w / S
        ws = ws[..., None] * tg.coord_weight[:, None, :]
    sub = "ntd" if ws.ndim == 3 else "nt"
    G_nn = torch.einsum(f"{sub},scntdi,scntdj->scnij", ws, new, new)
    h_n = torch.einsum(f"{sub},scntdi,ntd->scni", ws, new, tg.tau)
    if M:
        G_oo, h_o = normal_equations(basis, weights, tg)                   # N×X×X, N×X
        Phi0 = design(basis, weights, tg)                                  # N×T×n×X
        G_on = torch.einsum(f"{sub},ntdi,scntdj->scnij", ws, Phi0, new)        # S×C×N×X×(2+P)
        top = torch.cat([G_oo.expand(G_on.shape[:3] + G_oo.shape[-2:]), G_on], -1)
        bottom = torch.cat([G_on.transpose(-1, -2), G_nn], -1)
        G = torch.cat([top, bottom], -2)
        h = torch.cat([h_o.expand(h_n.shape[:3] + h_o.shape[-1:]), h_n], -1)
    else:
        G, h = G_nn, h_n
    x = nnls(G, h).x
    cost = quadratic_cost(G, h, x)
    return cost.sum(-1).transpose(0, 1)                                    # C×S


def best_candidate(basis, weights, tg, count: int, stiffnesses, generator,
                   chunk: int = 16):
    """(centre, stiffness, cost) of the best new field among data-driven candidates."""
    residual = residual_torques(basis, weights, tg)
    centres = candidate_centres(tg, residual, count, generator)
    costs = _finite(torch.cat([score_candidates(basis, weights, tg, centres[i:i + chunk], stiffnesses)
                               for i in range(0, centres.shape[0], chunk)]), tg)
    flat = int(costs.argmin())
    c, s = divmod(flat, costs.shape[1])
    return centres[c], float(stiffnesses[s]), float(costs[c, s])


def _finite(costs: torch.Tensor, tg: Targets) -> torch.Tensor:
    """Candidate costs with NaN as +∞ (a non-finite candidate is never chosen), warning
    once, naming the motions, when there were any."""
    bad = torch.isnan(costs)
    if bool(bad.any()):
        warnings.warn(f"search: {int(bad.sum())} candidate field(s) rejected: non-finite torque "
                      f"cost for {', '.join(tg.names)}", DivergenceWarning, stacklevel=3)
    return torch.where(bad, torch.full_like(costs, float("inf")), costs)


def field_shares(basis: FieldBasis, weights: MotionWeights, tg: Targets) -> torch.Tensor:
    """Each field's largest share (M) of a motion's model torque energy (the shares of
    one motion sum to ≤ 1), a chunk of motions at a time."""
    return by_chunks(_shares, basis, weights, tg).amax(0)


def _shares(basis: FieldBasis, weights: MotionWeights, tg: Targets) -> torch.Tensor:
    Phi = design(basis, weights, tg) * weights.vector()[:, None, None]    # N×T×n×M(2+P)
    M = basis.M
    per = Phi[..., :M] + Phi[..., M:2 * M] + Phi[..., 2 * M:].unflatten(-1, (M, weights.P)).sum(-1)
    e = (tg.wt[..., None] * (per ** 2).sum(-2)).sum(1)                                 # N×M
    return e / e.sum(-1, keepdim=True).clamp_min(1e-300)


@torch.no_grad()
def coincide(basis: FieldBasis, distance: float, stiffness: float) -> torch.Tensor:
    """M×M bools: whether fields i and k nearly coincide — centres within ``distance``
    (rad, Euclidean), stiffnesses within the fraction ``stiffness`` of field i's
    (‖K_i − K_k‖_F < stiffness · ‖K_i‖_F); every field coincides with itself."""
    eta, flat, exact = basis.eta.detach(), basis.K().detach().flatten(1), "donot_use_mm_for_euclid_dist"
    near = torch.cdist(eta, eta, compute_mode=exact) < distance
    return near & (torch.cdist(flat, flat, compute_mode=exact) < stiffness * flat.norm(dim=1, keepdim=True))


@torch.no_grad()
def merge_close(basis: FieldBasis, weights: MotionWeights, distance: float, stiffness: float):
    """Merge fields that nearly coincide: field k joins the cluster of the first field i <
    k that has not joined another's and whose centre is within
    ``distance`` of its own (rad, Euclidean) and whose stiffness differs from its own by
    less than the fraction ``stiffness`` (‖K_i − K_k‖_F < stiffness · ‖K_i‖_F); a
    cluster becomes one field with the mean centre and stiffness of its members, in its
    first member's place and with that member's weights. Many motions fitted alone find
    the same shared field many times over: each copy joins the first one's cluster.
    Returns new (basis, weights, merged pairs (first, other member)); the inputs are
    left unchanged."""
    eta, K = basis.eta.detach(), basis.K().detach()
    close = coincide(basis, distance, stiffness).triu(1)
    merged, used = [], set()
    for i in range(basis.M):
        if i in used:
            continue
        members = [k for k in close[i].nonzero().flatten().tolist() if k not in used]
        merged += [(i, k) for k in members]
        used |= {i, *members}
    if not merged:
        return basis, weights, []
    new_eta, new_K = eta.clone(), K.clone()
    for i in {i for i, _ in merged}:
        cluster = [i] + [k for j, k in merged if j == i]
        new_eta[i], new_K[i] = eta[cluster].mean(0), K[cluster].mean(0)
    keep = [i for i in range(basis.M) if i not in {k for _, k in merged}]
    return basis.like(new_eta[keep], new_K[keep]), weights.select_fields(keep), merged


def best_pairs(tg: Targets, template: FieldBasis, candidates: int, stiffnesses,
               generator: torch.Generator, top: int = 8, keep: int = 3, windows=None) -> list:
    """Multi-start for two fields at once: the ``top`` best single candidates (each with
    its best stiffness) are combined in pairs, every pair's weights solved by NNLS, and the
    ``keep`` best pairs returned as (basis, weights), bases like the empty ``template``
    (:meth:`~tflearn.model.fields.FieldBasis.like`). A second field added to a one-field fit
    starts from that fit's compromise; a pair found together need not. ``windows``: the
    motions' sub-movement windows (onsets, durations: N×P each), or None."""
    from .torque import solve_weights
    n = tg.q.shape[-1]
    b0, w0 = template, MotionWeights.zeros(0, tg.duration, tg.names, windows)
    centres = candidate_centres(tg, tg.tau, candidates, generator)
    costs = _finite(score_candidates(b0, w0, tg, centres, stiffnesses), tg)   # C×S
    best_k = costs.argmin(-1)
    order = costs.min(-1).values.argsort()[:top].tolist()
    eye = torch.eye(n, dtype=torch.float64)
    pairs = []
    for x, i in enumerate(order):
        for j in order[x + 1:]:
            eta = torch.stack([centres[i], centres[j]])
            K = torch.stack([float(stiffnesses[best_k[i]]) * eye, float(stiffnesses[best_k[j]]) * eye])
            basis = template.like(eta, K)
            weights = MotionWeights.zeros(2, tg.duration, tg.names, windows)
            cost = float(solve_weights(basis, weights, tg).sum())
            pairs.append((cost if math.isfinite(cost) else math.inf, len(pairs), basis, weights))
    pairs.sort(key=lambda p: p[:2])
    return [(b, w) for _, _, b, w in pairs[:keep]]


@dataclass(frozen=True)
class GrowOptions:
    """Settings of :func:`grow`. max_fields: the most fields it adds; tol: the relative
    torque cost C_j ≤ tol every motion must reach; candidates: data-driven centres scored
    per field; stiffnesses: the coarse stiffness grid each candidate is scored with;
    em_steps, em_tol: EM's steps and relative tolerance after each field joins; phases:
    EM also fits the activation timing; min_gain: a new field that lowers the summed
    cost by less than this fraction is not kept."""

    max_fields: int
    tol: float
    candidates: int
    stiffnesses: tuple
    em_steps: int
    em_tol: float = 1e-6
    phases: bool = False
    min_gain: float = 0.05


def grow(tg: Targets, template: FieldBasis, generator: torch.Generator, options: GrowOptions, *,
         reproduced=None, windows=None):
    """Greedy growth: add the best data-driven field and refine by EM, until every
    motion's relative torque cost is ≤ ``options.tol`` and ``reproduced(basis, weights)``
    (if given: a check by simulation) holds, there are ``options.max_fields`` fields, or a
    new field lowers the summed cost by less than the fraction ``options.min_gain`` (it is
    then not kept). ``template`` is an empty basis giving the fields' kind, blocks and
    damping; ``windows`` the motions' sub-movement windows (onsets, durations: N×P each,
    see :func:`~.targets.submovement_windows`) or None. Returns (basis, weights, costs per
    motion)."""
    from .torque import em, solve_weights
    n = tg.q.shape[-1]
    basis, weights = template, MotionWeights.zeros(0, tg.duration, tg.names, windows)
    costs = torch.ones(tg.N, dtype=torch.float64)
    while basis.M < options.max_fields:
        c, s, _ = best_candidate(basis, weights, tg, options.candidates, options.stiffnesses, generator)
        starts = [(basis.extend(c[None], s * torch.eye(n, dtype=torch.float64)[None]),
                   weights.extend_fields(1))]
        if basis.M == 1:
            starts += best_pairs(tg, template, options.candidates, options.stiffnesses, generator,
                                 windows=windows)
        fits = []
        for nb, nw in starts:
            em(nb, nw, tg, steps=options.em_steps, phases=options.phases, tol=options.em_tol)
            cost = float(solve_weights(nb, nw, tg).sum())
            fits.append((cost if math.isfinite(cost) else math.inf, len(fits), nb, nw))
        best, _, nb, nw = min(fits, key=lambda f: f[:2])
        if not math.isfinite(best):          # every start diverged: keep what we have
            warnings.warn(f"search: field {basis.M + 1} rejected: non-finite torque cost for "
                          f"{', '.join(tg.names)}", DivergenceWarning, stacklevel=2)
            break
        new_costs = solve_weights(nb, nw, tg)
        if basis.M and float(new_costs.sum()) > (1 - options.min_gain) * float(costs.sum()):
            break
        basis, weights, costs = nb, nw, new_costs
        if bool((costs <= options.tol).all()) and (reproduced is None or reproduced(basis, weights)):
            break
    return basis, weights, costs


def pool(tg: Targets, fits: list, template: FieldBasis):
    """One basis like ``template`` (an empty basis: kind, blocks, damping) holding the
    fields of the per-motion fits [(η M_j×n, K M_j×n×n, timing)], fit j being motion
    j's, and every motion's weights over them: its own fit's on its own fields where the
    fit holds them, zero elsewhere — not solved here, but after :func:`merge_close`,
    which keeps the many copies of a shared field from ever being in one design matrix.

    Motion j keeps the activation timing (and, where the fit holds them, the weights) it
    learned on its own fields (``timing``, from :meth:`MotionWeights.timing`) and its P
    sub-movement windows (P read from the timings); on the other motions' fields it
    starts at the default phases (step from t = 0, pulse over the whole motion)."""
    eta = torch.cat([fit[0] for fit in fits])
    K = torch.cat([fit[1] for fit in fits])
    basis = template.like(eta, K)
    z = torch.zeros(tg.N, len(fits[0][2]["window_onset"]), dtype=torch.float64)
    weights = MotionWeights.zeros(basis.M, tg.duration, tg.names, (z, z + 1))
    start = 0
    with torch.no_grad():
        for j, (e, _, timing) in enumerate(fits):
            for key, row in timing.items():
                if key in MotionWeights.WINDOWS:
                    getattr(weights, key)[j] = row
                else:
                    getattr(weights, key)[j, start:start + len(e)] = row
            start += len(e)
    return basis, weights
