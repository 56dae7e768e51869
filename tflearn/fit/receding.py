"""Receding-horizon path matching: a long motion's window weights fitted one window at a time.

Multiple shooting (:mod:`.shooting`) ends with single shooting over the whole motion on
every weight at once: D = M(2 + P) parameters, D + 1 simulations of the whole motion per
Jacobian, and P grows with the motion's length — a recorded clip of several seconds is
out of reach. Its windows, though, are local in time: window k's pulse
φ((t − o_k)/l_k) is 0 outside [o_k, o_k + l_k], so its weights c_·k move the path only
after o_k. Fitted in the order of their onsets, from the state the motion's own
simulation reaches, the whole motion becomes P small problems:

    for k = 0, 1, …, P_j − 1:
        x_k = the simulated state at s_k = o_k (the motion's first sample for k = 0)
        c_·k … c_·(k+A) ← argmin Σ_{t ∈ [s_k, e_k]} r_t²   (from x_k; the other weights held)
        e_k = o_{k+A} + l_{k+A}, the end of the last window fitted (the motion's end at most)

with the residuals r of :mod:`.shooting` (joints, β × velocities, γ × hand tip) on the
piece [s_k, e_k], Levenberg–Marquardt with bounds (:func:`.shooting.shooting_match` on
the piece as a motion of its own, ``ShootingOptions.windows``), A = ``ahead`` windows
beyond the k-th fitted with it (their weights only a start for the next step: a window's
effect is judged with what follows it). Each step costs M(A + 1) + 1 simulations of a
piece about (A + 1) windows long, so a motion costs time linear in its length, and the
result is one simulation: every piece starts where the motion's simulation under the
weights already fitted arrives, not on the target (tests/test_receding.py checks that a
piece so started continues that simulation). The starting weights need not simulate
the whole motion, only each piece; a motion whose single-shooting cost (the path
loss, and the hand's distance with a tip weight) ends above where it started gets its
starting weights back. A piece that cannot be
simulated ends its motion's fit there.
"""
from __future__ import annotations

import math
from dataclasses import replace
from typing import Callable, Optional

import torch

from ..model.fields import FieldBasis
from ..model.weights import MotionWeights
from ..physics.body import Body
from ..simulation.simulate import SimOptions, SimulationFailed
from . import shooting
from .targets import Targets, simulate_targets, trapezoid, union_grid

__all__ = ["pieces", "receding_match"]


def pieces(tg: Targets, motions: list, first: list, last: list, q0: torch.Tensor,
           v0: torch.Tensor) -> Targets:
    """Samples first[r] … last[r] of motion motions[r] as motions of their own, each
    shifted to start at t = 0 from the state (q0[r], v0[r]) (len(motions)×n) instead of
    the target's there; trapezoid weights of their own; the moving bases shifted with
    them."""
    m, k0, k1 = (torch.as_tensor(x, dtype=torch.long) for x in (motions, first, last))
    span = k1 - k0
    off = torch.arange(int(span.max()) + 1)
    idx = k0[:, None] + torch.minimum(off[None], span[:, None])
    mask = off[None] <= span[:, None]
    t0 = tg.t[m, k0]
    t = tg.t[m[:, None], idx] - t0[:, None]
    w = torch.stack([torch.where(mk, trapezoid(tr), torch.zeros(())) for tr, mk in zip(t, mask)])
    q, v = tg.q[m[:, None], idx].clone(), tg.v[m[:, None], idx].clone()
    q[:, 0], v[:, 0] = q0, v0
    grid, index = union_grid(t)
    return Targets(names=[tg.names[j] for j in motions], t=t, mask=mask, w=w, wt=w.clone(), q=q, v=v,
                   tau=tg.tau[m[:, None], idx], duration=t.amax(-1), q0=q0.clone(), qd0=v0.clone(),
                   grid=grid, index=index,
                   coord_weight=None if tg.coord_weight is None else tg.coord_weight[m],
                   base=None if tg.base is None else tg.base.take(m, shift=t0))


def _shifted(weights: MotionWeights, motions: list, t0: torch.Tensor) -> MotionWeights:
    """Motions ``motions`` of ``weights`` with every onset moved by −t0 (len(motions)):
    their programs on pieces that start at their own time t0."""
    out = weights.select_motions(motions)
    with torch.no_grad():
        for key in ("step_onset", "pulse_onset", "window_onset"):
            getattr(out, key).sub_(t0[:, None])
    return out


def _sample_at(tg: Targets, j: int, time: float) -> int:
    """The first sample of motion j at or after ``time`` (its last sample at most)."""
    L = int(tg.mask[j].sum())
    return min(L - 1, int(torch.searchsorted(tg.t[j, :L], torch.tensor(time - 1e-9, dtype=torch.float64))))


@torch.no_grad()
def receding_match(body: Body, basis: FieldBasis, weights: MotionWeights, tg: Targets, *,
                   options: shooting.ShootingOptions = shooting.ShootingOptions(receding=0.0),
                   sim: SimOptions = SimOptions(rtol=1e-6, atol=1e-8, max_evals=20000),
                   motions: Optional[list] = None,
                   callback: Optional[Callable] = None) -> shooting.ShootingResult:
    """Fit the window weights of ``motions`` (indices, default all; their P windows in
    order of their onsets, whatever their order in ``weights``) window by
    window (module docstring; ``options``' iterations, tol, floor, mu, step, sparse,
    velocity and tip weights and ``ahead``), the basis, a, b and the timing fixed;
    ``weights`` changed in place. The motions' k-th pieces are simulated together.
    ``callback(k, loss)`` after each step (loss: the pieces' path losses). Returns a
    :class:`~.shooting.ShootingResult`: each motion's cost at the end (single shooting,
    as :func:`~.shooting.shooting_match` reports it: the path loss, plus γ times the
    hand's with a tip weight; ∞ where the whole motion cannot be simulated) and why a
    motion's fit stopped early."""
    motions = list(range(tg.N)) if motions is None else list(motions)
    order = weights.window_onset.argsort(dim=1, stable=True)
    weights.permute_windows_(order)                          # in order of onset while fitted
    try:
        return _match(body, basis, weights, tg, options, sim, motions, callback)
    finally:
        weights.permute_windows_(order.argsort(dim=1))


def _match(body, basis, weights: MotionWeights, tg: Targets, options, sim, motions: list,
           callback) -> shooting.ShootingResult:
    """:func:`receding_match` on weights whose windows are in order of onset."""
    piece_opts = replace(options, horizon=math.inf, phases=False, fields=False, broyden=False, used=False,
                         receding=None)
    whole = shooting._Problem(body, basis, weights, tg, ("c_raw",), piece_opts, sim)   # single shooting
    longest = 2 * float(tg.duration.max())
    start = whole.theta()[motions]
    before = whole.cost(start, longest, motions).tolist()
    result = shooting.ShootingResult(loss=[])
    at = {j: (0, tg.q0[j], tg.qd0[j]) for j in motions}    # each piece's first sample and state
    for k in range(weights.P):
        live = [j for j in at if float(weights.window_onset[j, k]) < float(tg.duration[j])]
        if not live:
            break
        loss = _step(body, basis, weights, tg, live, k, at, piece_opts, sim, result)
        if callback:
            callback(k, loss)
    after = whole.cost(whole.theta()[motions], longest, motions).tolist()
    for r, j in enumerate(motions):
        if not after[r] <= before[r]:                       # never end further from the path
            weights.set_flat(("c_raw",), start[r:r + 1], [j])
            after[r] = before[r]
    result.loss, result.simulations = after, result.simulations + whole.simulations
    return result


def _step(body, basis, weights: MotionWeights, tg: Targets, live: list, k: int, at: dict,
          opts: shooting.ShootingOptions, sim: SimOptions, result: shooting.ShootingResult) -> list:
    """Step k of :func:`receding_match` on the motions ``live``: their pieces from ``at``
    (sample, q, v) to the end of window k + ``opts.ahead``, fitted, then simulated on to
    window k + 1's onset, where ``at`` moves (a motion leaves ``at`` at its end, or
    when its piece cannot be simulated, named in ``result.failures``). Returns the
    pieces' path losses."""
    last = min(k + opts.ahead, weights.P - 1)
    ends = [_sample_at(tg, j, float(weights.window_onset[j, last] + weights.window_duration[j, last]))
            for j in live]
    first = [at[j][0] for j in live]
    piece = pieces(tg, live, first, ends, torch.stack([at[j][1] for j in live]),
                   torch.stack([at[j][2] for j in live]))
    sub = _shifted(weights, live, tg.t[live, first])
    res = shooting.shooting_match(body, basis, sub, piece, sim=sim,
                                  options=replace(opts, windows=tuple(range(k, last + 1))))
    weights.set_flat(("c_raw",), sub.flat(("c_raw",)), live)
    result.simulations += res.simulations
    for r, (j, path) in enumerate(zip(live, _paths(body, basis, sub, piece, sim, result))):
        nxt = _sample_at(tg, j, float(weights.window_onset[j, k + 1])) if k + 1 < weights.P else None
        if isinstance(path, SimulationFailed):
            result.failures[tg.names[j]] = f"piece {k} not simulated: {path}"
        if nxt is None or nxt >= int(tg.mask[j].sum()) - 1 or isinstance(path, SimulationFailed):
            at.pop(j)
        else:
            i = max(nxt, first[r] + 1) - first[r]
            at[j] = (first[r] + i, path[0][i], path[1][i])
    return res.loss


def _paths(body, basis, sub: MotionWeights, piece: Targets, sim: SimOptions, result) -> list:
    """Each piece's simulated (q, v) (its samples × n each), or the SimulationFailed that
    stopped it: the pieces simulated together, then one by one where their batch fails."""
    result.simulations += 1
    try:
        return list(zip(*simulate_targets(body, basis, sub, piece, sim)))
    except SimulationFailed as err:
        if piece.N == 1:
            return [err]
    return [_paths(body, basis, sub.select_motions([r]), piece.select([r]), sim, result)[0]
            for r in range(piece.N)]
