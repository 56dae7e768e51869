"""Programs for motions on a frozen basis — the synthesis that held-out evaluation
(:func:`tflearn.evaluate.synthesize`) and training's rescue stage
(:mod:`tflearn.train.stages.rescue`) share:

1. weights by NNLS on each motion's torques (:func:`~tflearn.fit.torque.solve_weights`:
   exact, or with a ridge, or on some fields only), the basis fixed;
2. the motions those weights do not reproduce (:func:`unreproduced`: joint RMSE ≤
   ``success[0]`` rad and maximum tip error ≤ ``success[1]`` m, by simulation) get their
   weights — and with ``options.phases`` their activation timing — by multiple-shooting
   path matching (:func:`shoot`, :func:`tflearn.fit.shooting.shooting_match`);
3. of two programs for a motion, the one simulated closer is kept (:func:`closer`): one
   that reproduces it, else the one nearer the bar — the worse of joint RMSE and tip
   error, each against its own bar (a failed simulation is farthest).

:func:`fit_programs` runs 2–3 for new motions, with a second start for those still not
reproduced (the nearest of the basis' own programs, :func:`nearest_programs`).
:func:`held_ladder` gives each motion the first of several stiffness settings whose NNLS
weights reproduce it: the hold stage's (:mod:`tflearn.train.stages.hold`) and held-out
synthesis on a held basis. :func:`finer` cuts the motions still not reproduced into
more windows (``model.finer``): the path stage's and held-out synthesis'.
"""
from __future__ import annotations

from typing import Callable, Optional

import torch

from . import parallel
from .fit import impedance
from .fit.receding import receding_match
from .fit.shooting import ShootingOptions, keys_of, shooting_match
from .fit.targets import Targets, submovement_windows
from .fit.torque import torque_costs
from .metrics import Scores, score
from .model.weights import MotionWeights
from .simulation.simulate import SimOptions

#: The arrays of a motion's program: its weights on every field and its windows' timing.
PROGRAM = MotionWeights.PER_FIELD + MotionWeights.WINDOWS


def unreproduced(body, basis, weights: MotionWeights, tg: Targets, sim: SimOptions, success: tuple,
                 motions) -> tuple:
    """(the motions of ``motions`` (indices) that ``weights`` does not reproduce, how far
    each lies from the bar (:meth:`~tflearn.metrics.Scores.off_bar`)), the motions
    simulated together."""
    motions = list(motions)
    s = score(body, basis, weights.select_motions(motions), tg.select(motions), sim)
    far = s.off_bar(*success)
    bad = [r for r, ok in enumerate(s.succeeded(*success)) if not ok]
    return [motions[r] for r in bad], [far[r] for r in bad]


def shoot(body, basis, weights: MotionWeights, tg: Targets, motions: list, options: ShootingOptions,
          sim: SimOptions, distributed: bool = False,
          progress: Optional[Callable[[str], None]] = None) -> dict:
    """Multiple-shooting path matching of ``motions``' programs (indices; ``options``'
    arrays: weights, and timing with ``options.phases``), the basis fixed, ``weights``
    changed in place; those longer than ``options.receding`` (s) window by window
    (:func:`tflearn.fit.receding.receding_match`). ``distributed``: the motions shared by
    the ranks of a run and the results gathered, so that every rank holds every
    motion's. ``progress(where)`` is told where the fits are ("horizon 0.5 s",
    "window 3/40") after each iteration or window. Returns, per motion name,
    {"loss": the path loss left (None: ∞), "failure": why shooting stopped early, or None}."""
    keys = keys_of(options)
    mine = [motions[i] for i in parallel.mine(len(motions))] if distributed else list(motions)
    rows = {}
    for fit, part in _by_method(options, weights, tg, mine):
        res = fit(body, basis, weights, tg, options=options, sim=sim, motions=part,
                  callback=_told(progress, fit, weights.P))
        rows.update({j: {"theta": x.tolist(), "loss": loss if loss < float("inf") else None,
                         "failure": res.failures.get(tg.names[j])}
                     for j, x, loss in zip(part, weights.flat(keys)[part], res.loss)})
    rows = [rows[j] for j in mine]
    if distributed:
        rows = parallel.gather_motions(len(motions), rows)
        weights.set_flat(keys, torch.tensor([r["theta"] for r in rows], dtype=torch.float64), motions)
    return {tg.names[j]: {"loss": r["loss"], "failure": r["failure"]} for j, r in zip(motions, rows)}


def _told(progress: Optional[Callable[[str], None]], fit, P: int) -> Optional[Callable]:
    """``fit``'s callback that tells ``progress`` where it is (None without one)."""
    if progress is None:
        return None
    if fit is receding_match:
        return lambda k, loss: progress(f"window {k + 1}/{P}")
    return lambda h, it, cost: progress(f"horizon {h:.3g} s")


def _by_method(options: ShootingOptions, weights: MotionWeights, tg: Targets, motions: list) -> list:
    """[(fit, motions)]: the motions with windows longer than ``options.receding`` (s) to
    :func:`~tflearn.fit.receding.receding_match`, the others to
    :func:`~tflearn.fit.shooting.shooting_match` (none left out; empty groups dropped)."""
    long = [] if options.receding is None or not weights.P else \
        [j for j in motions if float(tg.duration[j]) > options.receding]
    rest = [j for j in motions if j not in long]
    return [(f, part) for f, part in ((shooting_match, rest), (receding_match, long)) if part]


def closer(before: list, after: Scores, success: tuple, ok: Optional[list] = None) -> list:
    """Per motion, whether the programs ``after`` was scored with simulate it closer than
    programs ``before`` (each motion's distance from the bar ``success``,
    :meth:`~tflearn.metrics.Scores.off_bar`): ``after`` reproduces it (``ok``, when
    given), or its simulation ends nearer the bar — the worse of joint RMSE and tip
    error, each against its own bar (a failed simulation never does)."""
    ok = ok or [False] * len(before)
    return [o or d < d0 for o, d, d0 in zip(ok, after.off_bar(*success), before)]


def take(weights: MotionWeights, source: MotionWeights, rows: list, into: list) -> None:
    """Motions ``into`` of ``weights`` take the programs of motions ``rows`` of ``source``."""
    weights.set_flat(PROGRAM, source.flat(PROGRAM)[rows], into)


def recut(body, basis, weights: MotionWeights, tg: Targets, rows: list, rate: float,
          asked: impedance.Impedance, ridge: float = 0.0) -> tuple:
    """(new weights of motions ``rows`` cut into ``rate`` sub-movement windows a second, up
    to ``weights.P`` (:func:`~tflearn.fit.targets.submovement_windows`), solved by NNLS on
    their torques and the stiffness ``asked`` (:func:`~tflearn.fit.impedance.solve_weights`);
    those motions' targets)."""
    part = tg.select(rows)
    sub = weights.select_motions(rows).with_windows(*submovement_windows(part, weights.P, rate=rate))
    impedance.solve_weights(body, basis, sub, part, asked, ridge=ridge)
    return sub, part


def finer(body, basis, weights: MotionWeights, tg: Targets, todo: dict, rates: list,
          asked: impedance.Impedance, shoot: Callable, judge: Callable, success: tuple,
          ridge: float = 0.0, told: Optional[Callable] = None) -> dict:
    """Activation sequences sized by what each motion needs: motions ``todo`` (index →
    how far their closest program so far lies from the bar ``success``,
    :meth:`~tflearn.metrics.Scores.off_bar`) are cut at each window rate of
    ``rates`` in turn (:func:`recut`: NNLS on their torques and the stiffness ``asked``),
    shot (``shoot(weights, tg)`` of those motions, in place) and judged (``judge(weights,
    tg)`` → (:class:`~tflearn.metrics.Scores`, reproduced per motion)); a motion keeps
    the new program where it simulates closer (:func:`closer`), in ``weights`` (in
    place), and leaves the ladder once reproduced. ``told(rate, count)`` hears each rung.
    Returns {motion index: the window rate it kept}."""
    kept = {}
    for rate in rates:
        if not todo:
            break
        rows = list(todo)
        sub, part = recut(body, basis, weights, tg, rows, rate, asked, ridge)
        if told is not None:
            told(rate, len(rows))
        shoot(sub, part)
        after, now = judge(sub, part)
        better = [r for r, b in enumerate(closer(list(todo.values()), after, success, now)) if b]
        take(weights, sub, better, [rows[r] for r in better])
        kept.update({rows[r]: rate for r in better})
        far = after.off_bar(*success)
        todo = {j: far[r] if r in better else todo[j] for r, j in enumerate(rows) if not now[r]}
    return kept


def held_ladder(body, basis, weights: MotionWeights, tg: Targets, settings: list, judge: Callable,
                ridge: float = 0.0) -> tuple:
    """Each motion's held program, in ``weights`` (in place): for each (window rate,
    :class:`~tflearn.fit.impedance.Impedance`) of ``settings`` in turn, the NNLS weights of
    the motions not yet reproduced (:func:`~tflearn.fit.impedance.solve_weights`, cut into
    that many windows a second, up to ``weights.P``), which ``judge(weights, tg)`` — of
    those motions — answers with (why each simulation failed or None, reproduced per
    motion); a motion keeps the first setting that reproduces it, else the last. Returns
    (the setting each motion took, None where none reproduces it; reproduced per motion;
    why its last simulation failed, None where it did not)."""
    chosen, ok, failures = [None] * tg.N, [False] * tg.N, [None] * tg.N
    for rate, asked in settings:
        todo = [j for j in range(tg.N) if not ok[j]]
        if not todo:
            break
        sub, part = recut(body, basis, weights, tg, todo, rate, asked, ridge)
        failed, now = judge(sub, part)
        take(weights, sub, list(range(len(todo))), todo)
        for r, j in enumerate(todo):
            failures[j] = failed[r]
            if now[r]:
                chosen[j], ok[j] = (rate, asked), True
    return chosen, ok, failures


def nearest_programs(basis, trained: MotionWeights, tg: Targets) -> MotionWeights:
    """For each motion of ``tg``, the program of one of the basis' own motions
    (``trained``: their weights and activation timing, onsets and durations scaled by the
    ratio of the two motions' durations) whose torques match it best: the lowest relative
    torque cost C_j (:func:`~tflearn.fit.torque.torque_cost`) over the basis' motions. A
    start for path matching where the new motion's own NNLS weights make a program that
    cannot be simulated along it."""
    keys = MotionWeights.TIMING + MotionWeights.WINDOWS

    def programs(rows):                  # motion rows[j]'s program, for motion j of tg
        w = trained.select_motions(rows)
        w.set_flat(keys, w.flat(keys) * (tg.duration / w.duration)[:, None], range(tg.N))
        w.duration.copy_(tg.duration)
        w.names = list(tg.names)
        return w
    costs = [torque_costs(basis, programs([k] * tg.N), tg) for k in range(trained.N)]
    return programs(torch.stack(costs, 1).argmin(1).tolist())


def fit_programs(body, basis, weights: MotionWeights, tg: Targets, options: ShootingOptions,
                 sim: SimOptions, success: tuple,
                 second: Optional[Callable[[Targets], MotionWeights]] = None) -> dict:
    """Steps 2–3 for every motion of ``tg`` whose ``weights`` (step 1's, changed in place)
    do not reproduce it: shot from them; those still not reproduced are shot again from
    ``second(their targets)`` (other programs for them), and each keeps whichever of the
    first fit, the second, or the second's start as it is simulates closest. Returns, per
    motion, why the shooting of the fit it kept stopped early (or, where it kept the
    second's start, that no fit came closer)."""
    todo = unreproduced(body, basis, weights, tg, sim, success, range(tg.N))[0]
    if not todo:
        return {}
    failures = {name: r["failure"] for name, r in shoot(body, basis, weights, tg, todo, options, sim).items()
                if r["failure"]}
    still, far = unreproduced(body, basis, weights, tg, sim, success, todo)
    if not still or second is None:
        return failures
    sub = tg.select(still)
    alt = second(sub)
    start = alt.select_motions(range(sub.N))                # the second's start as it is
    again = {name: r["failure"] for name, r in shoot(body, basis, alt, sub, list(range(sub.N)), options,
                                                     sim).items() if r["failure"]}
    kept = [None] * sub.N
    for program, s in [(w, score(body, basis, w, sub, sim)) for w in (alt, start)]:
        for r, (better, d) in enumerate(zip(closer(far, s, success), s.off_bar(*success))):
            if better:
                kept[r], far[r] = program, d
    for r, (name, j) in enumerate(zip(sub.names, still)):
        if kept[r] is not None:
            take(weights, kept[r], [r], [j])
            failures.pop(name, None)
            if name in again or kept[r] is start:
                failures[name] = again.get(name, "no fit came closer than the nearest trained program "
                                                 "as it is")
    return failures
