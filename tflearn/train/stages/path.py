"""Stage ``path`` — path matching for the motions not yet reproduced: first each one's
weights (and with ``model.phases: variable`` its timing) by multiple shooting and
Levenberg–Marquardt, the basis fixed (``solver.shooting``, :mod:`tflearn.fit.shooting`;
one unit, the motions shared by the ranks), then, if some are still not reproduced,
safeguarded Adam on the simulated path loss Σ_j L_j of fields and weights through
``odeint`` (:func:`tflearn.fit.path.path_step`; ``solver.path``; one unit per step). The
run's result is then the best point Adam found (:func:`~tflearn.train.models.final_model`).
"""
from __future__ import annotations

from functools import partial

from ... import synthesis
from ...fit import impedance
from ...fit import path as path_fit
from ...model.program import model_from_state, model_state
from ..context import RunContext
from ..state import PathProgress, RunState

NAME, TITLE, UNIT = "path", "path matching", "steps"


def run(ctx: RunContext, state: RunState) -> None:
    """The start (:func:`start`), then one Adam step and its checkpoint; on to the next
    stage once every motion is reproduced, the steps are done, or the simulation fails
    at the start."""
    p, tg = ctx.cfg.solver.path, ctx.tg
    basis, weights = model_from_state(state.model)
    ctx.log.stage(NAME, p.steps, state.cursor)
    if state.path is None:
        start(ctx, state, basis, weights)
    if not state.path.needed or state.cursor >= p.steps:
        ctx.log.end_stage()
        return state.advance(ctx.sequence)
    ctx.log.busy(step=state.cursor + 1)
    res = path_fit.path_step(ctx.body, basis, weights, tg, lr=state.path.lr, best=state.path.best,
                             optimizer_state=state.path.optimizer, velocity_weight=p.velocity_weight,
                             phases=ctx.variable_phases, options=ctx.options,
                             fields=state.path.motions is None, motions=state.path.motions,
                             distributed=True)
    if res.best is None:                 # the simulation fails at the starting point
        state.history.path = res.failure
        ctx.log.status(advance=0, failed="the simulation fails at the start")
        ctx.log.end_stage()
        return state.advance(ctx.sequence)
    state.path.lr, state.path.best, state.path.optimizer = res.lr, res.best, res.optimizer
    state.model = model_state(basis, weights)
    step = ctx.tick(state)
    ctx.log.scalar("path/loss", res.loss, step)
    ctx.log.scalar("path/lr", res.lr, step)
    ctx.log.model(basis, weights, step)
    ctx.log.status(loss=res.loss, lr=res.lr)
    state.cursor += 1
    ctx.save(state)


def start(ctx: RunContext, state: RunState, basis, weights) -> None:
    """The model that elimination left, scored; the motions it does not reproduce shot
    (``solver.shooting``; one iteration, logged with the paths' figures, and its own
    checkpoint: a resumed run does not shoot again); then whether Adam steps are needed
    and for which motions (``solver.path.motions``). A motion of those whose simulation
    fails in the scoring fails Adam's start too (its evaluations are no fewer with a
    gradient): no step is taken, and its failure is the stage's, recorded without
    simulating every motion with its gradient's graph."""
    p, tg = ctx.cfg.solver.path, ctx.tg
    scores, ok = ctx.check(basis, weights, tg)
    shoot = not all(ok) and ctx.cfg.solver.shooting.iterations
    if shoot:
        ctx.shoot(state, basis, weights, [j for j, x in enumerate(ok) if not x])
        scores, ok = ctx.check(basis, weights, tg)
        if ctx.cfg.model.finer and not all(ok):
            finer(ctx, state, basis, weights, scores, ok)
            scores, ok = ctx.check(basis, weights, tg)
        ctx.log.scores(scores, tg, ctx.tick(state), figures=True)
        state.model = model_state(basis, weights)
    state.path = PathProgress(needed=not all(ok), lr=p.lr,
                              motions=[j for j, x in enumerate(ok) if not x] if p.motions == "unreproduced"
                              else None)
    failed = [j for j in (state.path.motions or range(tg.N)) if scores.failure[j] is not None]
    if not state.path.needed:
        ctx.log.status(advance=0, total=0, skipped="every motion reproduced")
    elif failed:
        # Adam would simulate these with their gradients' graph until their evaluation
        # budget ran out (gigabytes at high sample rates), to fail at the start all the same
        state.path.needed = False
        state.history.path = "; ".join(f"{scores.failure[j]} (motion {tg.names[j]})" for j in failed)
        ctx.log.status(advance=0, failed="the simulation fails at the start")
    if shoot:
        ctx.save(state)


def finer(ctx: RunContext, state: RunState, basis, weights, scores, ok: list) -> None:
    """Activation sequences sized by what each motion needs: a motion that shooting left
    unreproduced is cut into ``model.window_rate`` × 2ᵏ sub-movement windows a second,
    k = 1 … ``model.finer``, with the stiffness about the path that ``solver.layout``
    asks for a laid-out basis, and shot again (:func:`~tflearn.synthesis.finer`; the
    motions shared by the ranks); it keeps the new program where that simulates closer,
    in ``weights`` (in place). ``history.finer``: the windows a second each such motion
    kept."""
    tg, m = ctx.tg, ctx.cfg.model
    asked = ctx.cfg.solver.layout.impedance() if ctx.cfg.solver.method == "layout" else impedance.Impedance()
    options = ctx.cfg.solver.shooting.options(ctx.variable_phases)
    success = (ctx.cfg.success.rmse, ctx.cfg.success.tip)
    far = scores.off_bar(*success)
    kept = synthesis.finer(
        ctx.body, basis, weights, tg, {j: far[j] for j, x in enumerate(ok) if not x},
        [m.window_rate * 2 ** k for k in range(1, m.finer + 1)], asked,
        shoot=lambda sub, part: synthesis.shoot(ctx.body, basis, sub, part, list(range(part.N)), options,
                                                ctx.options, distributed=True),
        judge=partial(ctx.check, basis), success=success, ridge=ctx.cfg.solver.ridge,
        told=lambda rate, n: ctx.log.busy(finer=f"{rate:g} windows/s", motions=n))
    state.history.finer = {tg.names[j]: rate for j, rate in kept.items()} or None
