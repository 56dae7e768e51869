"""Stage ``pool`` — all per-motion fields in one basis, every motion's weights re-solved
over all of them, so that no motion fits worse than alone (with ``solver.pool.sharing:
own`` each motion keeps to its own fields, as it was reproduced alone); fields that
nearly coincide (``solver.merge``) merged and refined jointly by EM.

Motions that their own fits reproduced but the pooled model does not get their own
fields back (:func:`restore`). The pooled model is scored by simulation: the reference
that elimination (``reduce``) keeps every motion to. One unit.
"""
from __future__ import annotations

from dataclasses import replace

import torch

from ...fit import search, torque
from ...metrics import Scores
from ...model.program import model_from_state, model_state
from ...model.weights import MotionWeights
from ..context import RunContext
from ..models import weight_support
from ..state import ModelRecord, Reference, RunState

NAME, TITLE, UNIT = "pool", "pool and merge", "stage"


def run(ctx: RunContext, state: RunState) -> None:
    """Pool, merge, refine, solve the weights (one iteration), restore, score; the
    reference of ``reduce``; one checkpoint."""
    tg, merge, c = ctx.tg, ctx.cfg.solver.merge, ctx.cfg.solver.pool
    ctx.log.stage(NAME, 1)
    basis, weights = search.pool(tg, state.fits, ctx.template())
    if c.sharing == "own":                          # each motion on its own fields
        ends = torch.tensor([len(f.eta) for f in state.fits]).cumsum(0).tolist()
        state.support = [[lo <= i < hi for i in range(basis.M)] for lo, hi in zip([0] + ends, ends)]
    basis, weights, merged = search.merge_close(basis, weights, merge.distance, merge.stiffness)
    if merged and state.support is not None:        # a merged cluster: its motions may use it
        drop = {k for _, k in merged}
        for row in state.support:
            for i, k in merged:
                row[i] = row[i] or row[k]
        state.support = [[x for i, x in enumerate(row) if i not in drop] for row in state.support]
    if merged or ctx.variable_phases:               # other motions' phases: default
        ctx.em(basis, weights, tg, state, tag="torque_cost/pool", support=state.support, min_gain=c.min_gain)
    cost = float(torque.solve_weights(basis, weights, tg, weight_support(state.support, weights.P)).sum())
    scores, ok = ctx.check(basis, weights, tg)
    state.model = model_state(basis, weights)
    state.history.pool = ModelRecord(M=basis.M, torque_cost=cost, success=ok, merged=merged)
    scores, ok = restore(ctx, state, scores, ok)
    step = ctx.tick(state)
    ctx.log.scalar("torque_cost/pool", cost, step)
    ctx.log.scores(scores, tg, step, figures=True)
    ctx.log.model(*model_from_state(state.model), step)
    state.fits = []                                  # read by no later stage: not saved again
    state.reference = Reference.of(scores, ok)
    if ctx.cfg.solver.reduce.growth is not None:
        state.reference.efolds = ctx.efolds(*model_from_state(state.model), tg)
    pooled = state.history.pool
    ctx.log.status(M=pooled.M, merged=len(merged), cost=cost, restored=len(pooled.restored or []),
                   reproduced=f"{sum(ok)}/{tg.N}")
    ctx.log.end_stage()
    state.advance(ctx.sequence)
    ctx.save(state)


def restore(ctx: RunContext, state: RunState, scores: Scores, ok: list) -> tuple:
    """Motions their own fits reproduced (``each``) that the pooled model does not —
    merging or refitting moved a field their path needs to the digit — get their own
    fields back as fields of their own: such a motion's weights and timing are its own
    fit's, on those fields only, and no other motion uses them (``state.support``);
    elimination may still remove them, by its rule. Changes ``state.model``,
    ``state.support`` and the pool's record; returns the (scores, success) of every
    motion."""
    tg = ctx.tg
    alone = state.history.each.reproduced if state.history.each else []
    broken = [j for j, (a, o) in enumerate(zip(alone, ok)) if a and not o]
    if not broken:
        return scores, ok
    basis, weights = model_from_state(state.model)
    M0, own = basis.M, [state.fits[j] for j in broken]
    nb = basis.extend(torch.cat([f.eta for f in own]), torch.cat([f.K for f in own]))
    nw = weights.extend_fields(nb.M - M0)
    rows = state.support or [[True] * M0 for _ in range(tg.N)]
    support = [row + [False] * (nb.M - M0) for row in rows]
    start = M0
    with torch.no_grad():
        for j, (eta, _, fit) in zip(broken, own):
            for key in ("a_raw", "b_raw", "c_raw"):
                getattr(nw, key)[j] = 0.0
            for key, row in fit.items():
                target = getattr(nw, key)
                if key in MotionWeights.WINDOWS:
                    target[j] = row
                else:
                    target[j, start:start + len(eta)] = row
            support[j] = [start <= i < start + len(eta) for i in range(nb.M)]
            start += len(eta)
    check, fine = ctx.check(nb, nw.select_motions(broken), tg.select(broken))
    scores, ok = _replaced(scores, broken, check), list(ok)
    for i, j in enumerate(broken):
        ok[j] = fine[i]
    state.model, state.support = model_state(nb, nw), support
    record = state.history.pool
    record.M, record.success, record.restored = nb.M, ok, [tg.names[j] for j in broken]
    return scores, ok


def _replaced(scores: Scores, motions: list, check: Scores) -> Scores:
    """``scores`` with the rows of ``motions`` those of ``check`` (their scores, in order)."""
    keys = ("rmse", "tip", "torque", "failure")
    out = replace(scores, q_sim=scores.q_sim.clone(), **{k: list(getattr(scores, k)) for k in keys})
    for i, j in enumerate(motions):
        for key in keys:
            getattr(out, key)[j] = getattr(check, key)[i]
        out.q_sim[j] = check.q_sim[i, :out.q_sim.shape[1]]
    return out
