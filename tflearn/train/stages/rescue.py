"""Stage ``rescue`` (``solver.rescue.enabled``) — motions still not reproduced get a
spanning layout's fields laid out around them (:func:`tflearn.fit.layout.spanning_basis`)
added to the basis, and programs on it by the synthesis service
(:mod:`tflearn.synthesis`): weights by NNLS on those fields, then multiple shooting
over the whole basis (``solver.rescue``'s settings); when the new fields reproduce at
least one motion they are kept, and a motion keeps its new program if it reproduces it
or comes closer; those still not reproduced get a layout of their own in the next round
(fields that reproduce nothing are not kept: they would only grow the basis). One unit
per round, at most ``solver.rescue.rounds``, until a round keeps nothing.
"""
from __future__ import annotations

from dataclasses import replace

from ... import synthesis
from ...fit import torque
from ...fit.targets import inertia_weights
from ...metrics import Scores
from ...model.program import model_from_state, model_state
from ..context import RunContext
from ..models import final_model, layout_basis, weight_support
from ..state import RescueRound, RunState

NAME, TITLE, UNIT = "rescue", "rescue: spanning fields for motions not reproduced", "stage"


def run(ctx: RunContext, state: RunState) -> None:
    """Rounds of :func:`rescue_round` (one iteration and one checkpoint each) on the
    motions the run's result still does not reproduce, until every motion is reproduced,
    a round improves none, or the motions left are the last round's (a layout depends on
    its motions alone: it would lay out the same fields again)."""
    tg, rounds = ctx.tg, ctx.cfg.solver.rescue.rounds
    while state.cursor < rounds:
        basis, weights = final_model(state)
        scores, ok = ctx.check(basis, weights, tg)
        last = state.history.rescue[-1].motions if state.history.rescue else None
        if all(ok) or last == [n for n, x in zip(tg.names, ok) if not x]:
            break
        ctx.log.stage(NAME, rounds, state.cursor)
        record = rescue_round(ctx, state, basis, weights, scores, ok)
        state.history.rescue.append(record)
        state.cursor += 1
        step = ctx.tick(state)
        if record.kept:
            ctx.log.model(*model_from_state(state.model), step)
        ctx.log.status(M=record.M, reproduced=f"{sum(ok) + len(record.reproduced)}/{tg.N}", kept=record.kept)
        if not record.kept:
            break
        ctx.save(state)
    ctx.log.end_stage()
    state.advance(ctx.sequence)
    ctx.save(state)


def rescue_round(ctx: RunContext, state: RunState, basis, weights, scores: Scores, ok: list) -> RescueRound:
    """The motions that ``basis``, ``weights`` do not reproduce (``scores``, ``ok``) get
    fields laid out around them (``solver.rescue``'s layout) added to the basis; their
    weights start on the new fields alone, by NNLS (its ridge and torque weights), and
    multiple shooting (``solver.shooting``'s horizon, ``solver.rescue``'s iterations, tip
    and velocity weights) then fits them over the whole basis (with
    ``solver.shooting.used``, over the new fields their weights are on). If the new
    fields reproduce some motion, a motion takes its new program where that is closer
    (:func:`tflearn.synthesis.closer`: it reproduces the motion, or is simulated nearer
    the bar); the others keep theirs, with zero weight on the new fields. The grown model
    becomes the run's result if some motion took its new program; returns the round's
    record."""
    r, tg = ctx.cfg.solver.rescue, ctx.tg
    todo = [j for j, x in enumerate(ok) if not x]
    sub = tg.select(todo)
    sub = replace(sub, coord_weight=inertia_weights(ctx.body, sub) if r.torque_weight == "inertia" else None)
    laid = layout_basis(ctx.cfg, ctx.body, sub, r)
    grown, more = basis.extend(laid.eta, laid.K()), weights.extend_fields(laid.M)
    subw = more.select_motions(todo)
    new = weight_support([[False] * basis.M + [True] * laid.M] * len(todo), subw.P)
    torque.solve_weights(grown, subw, sub, ridge=r.ridge, support=new)
    synthesis.take(more, subw, list(range(len(todo))), todo)
    opts = replace(ctx.cfg.solver.shooting.options(ctx.variable_phases), iterations=r.iterations,
                   tip_weight=r.tip_weight, velocity_weight=r.velocity_weight)
    ctx.shoot(state, grown, more, todo, opts)
    after, now = ctx.check(grown, more, tg)
    success = (ctx.cfg.success.rmse, ctx.cfg.success.tip)
    better = synthesis.closer(scores.off_bar(*success), after, success, now)
    if not any(now[j] for j in todo):     # fields that reproduce nothing are not kept
        better = [False] * tg.N
    took, back = [j for j in todo if better[j]], [j for j in todo if not better[j]]
    if back:
        synthesis.take(more, weights.extend_fields(laid.M), back, back)
    if took:                              # the run's result from here (not path's best)
        state.model, state.path.best = model_state(grown, more), None
    return RescueRound(motions=[tg.names[j] for j in todo], added=laid.M, M=grown.M if took else basis.M,
                       reproduced=[tg.names[j] for j in todo if now[j]],
                       improved=[tg.names[j] for j in took], kept=bool(took))
