"""Stage ``pool`` — all per-motion fields in one basis; the shared fields chosen among
them by what the motions need (``solver.select``, :func:`~tflearn.fit.select.select`:
the fewest that keep every motion its own fit reproduced within its own fit's torque
cost plus δ — the cost of its fewest own fields that simulation reproduces, where that
is higher: :func:`_reproducing_costs`), refined jointly by EM and chosen again among
the refined ones; with ``solver.select.enabled: false`` fields that nearly coincide
(``solver.merge``) are merged instead, every other pooled field kept (with
``solver.pool.sharing: own`` each motion keeps to its own fields, as it was reproduced
alone).

Motions that their own fits reproduced but the chosen basis does not are first
path-matched on it by multiple shooting (:func:`shoot`); if that fails their fewest
chosen fields are fitted to their paths and to those of other motions that drive them,
all at once (:func:`share`); and if that fails too they get fields of their own
(:func:`restore`): copies of their fewest chosen fields fitted to their path, or their
own fit's. The pooled model is scored by simulation: the reference that elimination
(``reduce``) keeps every motion to. One unit.
"""
from __future__ import annotations

from typing import Optional

import torch

from ... import parallel
from ...fit import search, select, torque
from ...metrics import Scores
from ...model.program import model_from_state, model_state
from ...plots.model import knee
from ..context import RunContext
from ..models import weight_support
from ..state import FieldFit, ModelRecord, Reference, RunState

NAME, TITLE, UNIT = "pool", "pool and merge", "stage"


def run(ctx: RunContext, state: RunState) -> None:
    """Pool, choose the shared fields (or merge near-duplicates), refine, solve the
    weights (one iteration), restore, score; the reference of ``reduce``; one
    checkpoint."""
    tg, c = ctx.tg, ctx.cfg.solver.pool
    ctx.log.stage(NAME, 1)
    basis, weights = search.pool(tg, state.fits, ctx.template())
    ends = torch.tensor([len(f.eta) for f in state.fits]).cumsum(0).tolist()
    own = [[lo <= i < hi for i in range(basis.M)] for lo, hi in zip([0] + ends, ends)]
    chosen = tolerance = fewest = None
    if ctx.cfg.solver.select.enabled:
        basis, weights, merged, chosen, tolerance, fewest = _select(ctx, state, basis, weights, own)
    else:
        state.support = own if c.sharing == "own" else None
        basis, weights, merged = _merge(ctx, state, basis, weights)
    dropped = chosen is not None and chosen["kept"] < chosen["pooled"]
    if merged or dropped or ctx.variable_phases:    # other motions' phases: default
        ctx.em(basis, weights, tg, state, tag="torque_cost/pool", support=state.support, min_gain=c.min_gain)
    if dropped:
        basis, weights, fewest = _refined(ctx, state, basis, weights, chosen, tolerance)
    cost = float(torque.solve_weights(basis, weights, tg, weight_support(state.support, weights.P)).sum())
    scores, ok = ctx.check(basis, weights, tg)
    if chosen:
        scores, ok = shoot(ctx, state, basis, weights, scores, ok)
    state.model = model_state(basis, weights)
    state.history.pool = ModelRecord(M=basis.M, torque_cost=cost, success=ok, merged=merged or None,
                                     selection=chosen)
    if chosen:
        scores, ok = share(ctx, state, scores, ok, fewest)
    scores, ok = restore(ctx, state, scores, ok, fewest)
    step = ctx.tick(state)
    ctx.log.scalar("torque_cost/pool", cost, step)
    ctx.log.scores(scores, tg, step, figures=True)
    ctx.log.model(*model_from_state(state.model), step)
    state.fits = []                                  # read by no later stage: not saved again
    state.reference = Reference.of(scores, ok, required=required(state))
    if ctx.cfg.solver.reduce.growth is not None:
        state.reference.efolds = ctx.efolds(*model_from_state(state.model), tg)
    pooled = state.history.pool
    ctx.log.status(M=pooled.M, merged=len(merged), cost=cost, shared=len(pooled.shared or []),
                   restored=len(pooled.restored or []),
                   reproduced=f"{sum(ok)}/{tg.N}")
    ctx.log.end_stage()
    state.advance(ctx.sequence)
    ctx.save(state)


def _select(ctx: RunContext, state: RunState, basis, weights, own: list) -> tuple:
    """The fewest pooled fields that serve every motion (:func:`~tflearn.fit.select.select`):
    (basis, weights on them, merged pairs [kept, dropped] — each dropped own field with
    the nearest kept one its motion uses —, the selection's record for metrics.json, each
    motion's bar τ_j, each motion's fewest chosen fields that serve it). With ``sharing:
    own`` a motion may use the chosen fields among its candidates."""
    pooled, need = basis.M, required(state)
    floor = _reproducing_costs(ctx, basis, weights, own, need)
    ctx.log.busy(pooled=pooled, choosing="fields")
    sel = select.select(basis, weights, ctx.tg, torch.tensor(own), _options(ctx),
                        progress=lambda **done: ctx.log.busy(pooled=pooled, **done), distributed=True,
                        required=need, floor=floor)
    weights = weights.select_fields(sel.kept)
    state.support = ([[f in mine for f in sel.kept] for mine in sel.candidates]
                     if ctx.cfg.solver.pool.sharing == "own" else None)
    record = {"pooled": pooled, "kept": len(sel.kept), "pruned": len(sel.pruned),
              "candidates": sum(map(len, sel.candidates)) / max(len(sel.candidates), 1),
              "path": sel.path, "unserved": [ctx.tg.names[j] for j in sel.unserved],
              "unrequired": [ctx.tg.names[j] for j, r in enumerate(need or []) if not r]}
    if ctx.log.writer is not None:
        ctx.log.figure("model/knee", knee(sel.path, len(sel.kept), ctx.tg.N), state.iteration)
    return (basis.select(sel.kept), weights, sel.merged, record, sel.tolerance,
            _positions(sel.kept, sel.support))


def _reproducing_costs(ctx: RunContext, basis, weights, own: list, need: Optional[list]) -> list:
    """Each motion's torque cost on its fewest own fields that simulation reproduces
    (:func:`~tflearn.fit.select.reproducing_cost`; 0 for a motion not ``need``-ed), the
    selection's floor under its own fit's cost: an own fit that holds more fields fits
    its torque targets' own error too (the spline's, which can exceed δ), and a shared
    field need not. Each rank its share of the motions."""
    tg, mine = ctx.tg, parallel.mine(ctx.tg.N)

    def cost(i: int, j: int) -> float:
        ctx.log.busy(pooled=basis.M, floors=f"{i}/{len(mine)}")
        fields = [f for f, o in enumerate(own[j]) if o]
        if not fields or (need is not None and not need[j]):
            return 0.0
        one = tg.select([j])
        return select.reproducing_cost(basis, weights, tg, j, fields,
                                       lambda b, w: all(ctx.check(b, w, one, distributed=False)[1]))
    return parallel.gather_motions(tg.N, [cost(i, j) for i, j in enumerate(mine)])


def required(state: RunState) -> Optional[list]:
    """:meth:`EachRecord.required` of the run (None: no motion was fitted alone)."""
    return state.history.each.required() if state.history.each else None


def _positions(kept: list, support: list) -> list:
    """Each motion's fields (``support``: candidate indices) as positions in ``kept``."""
    where = {f: i for i, f in enumerate(kept)}
    return [[where[f] for f in mine] for mine in support]


def _options(ctx: RunContext) -> select.SelectOptions:
    o = ctx.cfg.solver.select
    return select.SelectOptions(tol=o.tol, reach=o.reach, block=o.block)


def _refined(ctx: RunContext, state: RunState, basis, weights, chosen: dict, tolerance: list) -> tuple:
    """EM has moved the chosen copies towards what all their motions need: the selection
    again among them, each motion held to the same bar τ_j (a copy that served few
    motions may now be served by a refined field), and each motion's fewest fields
    chosen again; if fewer remain, EM again. Returns (basis, weights, each motion's
    fewest fields); ``chosen`` records the count (``refined``)."""
    used = weights.used() | torch.tensor(state.support or [[False] * basis.M] * ctx.tg.N)
    sel = select.select(basis, weights, ctx.tg, used, _options(ctx), tolerance=tolerance, distributed=True,
                        required=required(state))
    chosen["refined"] = len(sel.kept)
    keep = sorted(sel.kept)
    fewest = _positions(keep, sel.support)
    if len(sel.kept) == basis.M:
        return basis, weights, fewest
    basis, weights = basis.select(keep), weights.select_fields(keep)
    if state.support is not None:
        state.support = [[row[i] for i in keep] for row in state.support]
    ctx.em(basis, weights, ctx.tg, state, tag="torque_cost/pool", support=state.support,
           min_gain=ctx.cfg.solver.pool.min_gain)
    return basis, weights, fewest


def _merge(ctx: RunContext, state: RunState, basis, weights) -> tuple:
    """Near-duplicates merged by distance (``solver.merge``): (basis, weights, merged
    pairs); a merged cluster's motions may use it (``state.support``)."""
    merge = ctx.cfg.solver.merge
    basis, weights, merged = search.merge_close(basis, weights, merge.distance, merge.stiffness)
    if merged and state.support is not None:
        drop = {k for _, k in merged}
        for row in state.support:
            for i, k in merged:
                row[i] = row[i] or row[k]
        state.support = [[x for i, x in enumerate(row) if i not in drop] for row in state.support]
    return basis, weights, merged


def broken(state: RunState, ok: list) -> list:
    """The motions their own fits reproduced (``each``) that ``ok`` says are not."""
    alone = state.history.each.reproduced if state.history.each else []
    return [j for j, (a, o) in enumerate(zip(alone, ok)) if a and not o]


def shoot(ctx: RunContext, state: RunState, basis, weights, scores: Scores, ok: list) -> tuple:
    """The chosen fields are right where their weights, solved on torques, are not quite
    (a motion whose simulation amplifies small torque errors): the :func:`broken` motions'
    weights by multiple shooting on the chosen basis (``solver.select.shooting``
    iterations, ``solver.shooting``'s other settings), ``weights`` changed in place;
    the (scores, success) of every motion after."""
    motions = broken(state, ok)
    if not motions or not ctx.cfg.solver.select.shooting:
        return scores, ok
    check, fine = ctx.path_matched(basis, weights, motions, state)
    ok = list(ok)
    for i, j in enumerate(motions):
        ok[j] = fine[i]
    return scores.replaced(motions, check), ok


def share(ctx: RunContext, state: RunState, scores: Scores, ok: list, fewest: list) -> tuple:
    """:func:`broken` motions' fewest chosen fields S (``fewest``) are a hair from where
    their paths need them: they are fitted by multiple shooting, free and shared, to
    their paths and to those of up to ``solver.select.users`` reproduced motions whose
    fewest fields share one with S (those S alone serves first), all at once, their
    other fields held (:func:`_moved`), and kept when simulation reproduces every one of
    them and every other reproduced motion with a weight on S (once its weights are
    path-matched on the moved fields where it must be, :func:`_kept`). The lost motions
    of one S are fitted together first (:func:`_groups`), and one by one where that
    fails. Such a motion then costs no field of its own. Changes ``state.model`` and the
    pool's record (``shared``: the motions so reproduced, by a last check of every motion
    whose program changed); returns the (scores, success) of every motion."""
    limit, lost = ctx.cfg.solver.select.users, broken(state, ok)
    if not lost or not limit:
        return scores, ok
    basis, weights = model_from_state(state.model)
    ok, shared, touched = list(ok), [], set()
    for group in _groups(lost, fewest):
        for js in [group] + ([[j] for j in group] if len(group) > 1 else []):
            js = [j for j in js if j not in shared]
            S = set(fewest[js[0]]) if js else set()
            near = sorted((k for k in range(ctx.tg.N) if k not in js and ok[k] and set(fewest[k]) & S),
                          key=lambda k: not set(fewest[k]) <= S)         # those S alone serves first
            if not js or not near:
                continue
            ctx.log.busy(sharing=ctx.tg.names[js[0]] + (f" and {len(js) - 1} more" if len(js) > 1 else ""),
                         users=len(near[:limit]))
            trial = _moved(ctx, state, basis, weights, js + near[:limit], fewest, ok, len(js))
            if trial is not None:
                basis, weights, moved = trial
                shared += js
                touched.update(moved)
    if not shared:
        return scores, ok
    moved = sorted(touched)
    check, fine = ctx.check(basis, weights.select_motions(moved), ctx.tg.select(moved))
    scores = scores.replaced(moved, check)
    for k, f in zip(moved, fine):
        ok[k] = f
    state.model = model_state(basis, weights)
    if state.support is not None:
        for j in shared:
            for i in fewest[j]:
                state.support[j][i] = True
    record = state.history.pool                       # those the check of all of them keeps
    record.success, record.shared = ok, [ctx.tg.names[j] for j in shared if ok[j]] or None
    return scores, ok


def _groups(lost: list, fewest: list) -> list:
    """The lost motions grouped by their fewest fields, in order of each group's first."""
    groups: dict = {}
    for j in lost:
        groups.setdefault(tuple(sorted(fewest[j])), []).append(j)
    return list(groups.values())


def _moved(ctx: RunContext, state: RunState, basis, weights, motions: list, fewest: list,
           ok: list, n: int = 1) -> Optional[tuple]:
    """The lost motions ``motions[:n]``' fewest fields S (theirs alike) fitted with
    their users (``motions[n:]``) by :meth:`RunContext.fit_shared` — once more without
    the users that fit loses, if it reproduces the lost ones —, then they and every
    other reproduced motion with a weight on S checked on the whole model (:func:`_kept`:
    a motion whose path amplifies round-off may not pass on the whole basis what it
    passed on S and its users' fields): (basis, weights, the motions whose programs
    changed), or None where any of them is not reproduced."""
    S = fewest[motions[0]]
    trial = ctx.fit_shared(basis, weights, motions, [fewest[k] for k in motions], S)
    if trial is not None and all(trial[2][:n]) and not all(trial[2]):
        motions = [k for k, f in zip(motions, trial[2]) if f]
        trial = ctx.fit_shared(basis, weights, motions, [fewest[k] for k in motions], S)
    if trial is None or not all(trial[2]):
        return None
    nb, nw, _ = trial
    others = [k for k in nw.used()[:, S].any(1).nonzero().flatten().tolist() if k not in motions]
    if not _kept(ctx, state, nb, nw, motions + [k for k in others if ok[k]]):
        return None
    return nb, nw, motions + others


def _kept(ctx: RunContext, state: RunState, basis, weights, motions: list) -> bool:
    """Whether simulation reproduces every one of ``motions`` on the model, those it does
    not first path-matched by multiple shooting (as in :func:`shoot`, ``weights``
    changed in place)."""
    if not motions:
        return True
    lost = [k for k, f in zip(motions, ctx.check(basis, weights.select_motions(motions),
                                                  ctx.tg.select(motions))[1]) if not f]
    if not lost or not ctx.cfg.solver.select.shooting:
        return not lost
    return all(ctx.path_matched(basis, weights, lost, state)[1])


def restore(ctx: RunContext, state: RunState, scores: Scores, ok: list,
            fewest: Optional[list] = None) -> tuple:
    """Motions their own fits reproduced (``each``) that the pooled model does not —
    merging or refitting moved a field their path needs to the digit — get fields of
    their own, which no other motion uses (``state.support``): copies of the fields they
    drive (``fewest``: each motion's fewest fields that serve it, from the selection;
    else those it has a weight on), fitted to their path by multiple shooting with the
    fields free (:func:`_fitted_copies`) when that reproduces them, else their own fit's
    fields, weights and timing. Elimination may still remove them, by its rule. Changes
    ``state.model``, ``state.support`` and the pool's record (``restored``: every such
    motion; ``copied``: those on fitted copies); returns the (scores, success) of every
    motion."""
    tg, lost = ctx.tg, broken(state, ok)
    if not lost:
        return scores, ok
    basis, weights = model_from_state(state.model)
    ctx.log.busy(restoring=len(lost))
    drives = fewest or [row.nonzero().flatten().tolist() for row in weights.used()]
    copies = parallel.gather_motions(len(lost), [_fitted_copies(ctx, basis, weights, lost[i], drives[lost[i]])
                                                 for i in parallel.mine(len(lost))])
    M0, own = basis.M, [c or state.fits[j] for c, j in zip(copies, lost)]
    nb = basis.extend(torch.cat([f.eta for f in own]), torch.cat([f.K for f in own]))
    nw = weights.extend_fields(nb.M - M0)
    rows = state.support or [[True] * M0 for _ in range(tg.N)]
    support = [row + [False] * (nb.M - M0) for row in rows]
    start = M0
    for j, (eta, _, fit) in zip(lost, own):
        nw.put_(j, list(range(start, start + len(eta))), fit)
        support[j] = [start <= i < start + len(eta) for i in range(nb.M)]
        start += len(eta)
    check, fine = ctx.check(nb, nw.select_motions(lost), tg.select(lost))
    scores, ok = scores.replaced(lost, check), list(ok)
    for i, j in enumerate(lost):
        ok[j] = fine[i]
    state.model, state.support = model_state(nb, nw), support
    record = state.history.pool
    record.M, record.success = nb.M, ok
    record.restored = [tg.names[j] for j in lost]
    record.copied = [tg.names[j] for j, c in zip(lost, copies) if c is not None] or None
    return scores, ok


def _fitted_copies(ctx: RunContext, basis, weights, j: int, fields: list) -> Optional[FieldFit]:
    """Motion j alone on copies of ``fields`` (indices), its NNLS weights on
    them, copies and weights then fitted to its path by multiple shooting with the fields
    free (``solver.shooting``, as for a motion alone in ``each``): their
    :class:`FieldFit` when simulation then reproduces it, else None. A motion driven by
    one shared field costs one field of its own this way, not the two or three its own
    search found."""
    if not fields:
        return None
    one, b, w = ctx.tg.select([j]), basis.select(fields), weights.select_motions([j]).select_fields(fields)
    torque.solve_weights(b, w, one)
    if not ctx.shoot_fields(b, w, one) or not all(ctx.check(b, w, one, distributed=False)[1]):
        return None
    return FieldFit(b.eta.detach().clone(), b.K().detach().clone(), w.timing(0, weights=True))
