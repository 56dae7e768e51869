"""Experiment 5 (thesis §4.5.4 by class): filtering a motion through a basis learned on
its own kind.

A basis is learned on a class of motions — minimum-jerk straight-line hand reaches from
rest to targets spread over the space in front of the arm (:func:`reach_class`) — by
each method of ``cfg.methods``: the pipeline's search, or the spanning layout
(``cfg.training("layout")``, :mod:`tflearn.fit.layout`). A held-out reach of the same
class is then played through each basis frozen: its weights by NNLS on its torques, then
its weights and activation timing by multiple-shooting path matching
(:func:`tflearn.evaluate.synthesize`). Goals: the class's reaches reproduced, and the
held-out reach within 0.05 rad joint RMSE of its input. The hand paths' largest
deviation from their chords (:func:`.filtering.straightness`) shows what the fields add.
"""
from __future__ import annotations

import math
import time
from pathlib import Path

import torch

from ..data.keyframes import straight_reach
from ..evaluate import synthesize
from ..fit.targets import prepare
from ..io import basis as basis_io
from ..physics import dynamics
from ..physics.body import Body, arm
from ..simulation import simulate as sim_mod
from . import common
from .config import ExperimentConfig
from .filtering import draw, filtered_table, straightness

TEXT = common.text("reaches")
GOAL_RMSE = 0.05                          # rad, the held-out reach against its input
SCALES = (0.7, 0.85)                      # target distance, fraction of the arm's straight-ahead reach
TURNS = (-0.6, -0.2, 0.2, 0.6)            # rad about the vertical
HELD_OUT = (0.78, 0.0)                    # inside the class: between its scales and turns
DURATION = 2.0                            # s


def thesis() -> str:
    """The thesis' outcome, in words."""
    return TEXT["thesis"]


def targets(body: Body, scales=SCALES, turns=TURNS) -> dict:
    """{name: hand target (3)}: ``scale`` × the straight-ahead point of the stiff-elbow
    lift (the arm's full forward reach) turned by ``turn`` about the vertical, for every
    scale × turn, and the held-out reach's."""
    ahead = dynamics.tip_position(body, common.gesture_motions(body, ["stiff_elbow_lift"])
                                  ["stiff_elbow_lift"].q[-1])

    def point(scale, turn):
        c, s = math.cos(turn), math.sin(turn)
        Rz = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=common.F64)
        return scale * Rz @ ahead
    out = {f"reach_{s:g}_{t:+g}": point(s, t) for s in scales for t in turns}
    out["held_out_reach"] = point(*HELD_OUT)
    return out


def reach_class(body: Body, scales=SCALES, turns=TURNS) -> tuple:
    """(the class: a straight-line reach from rest to every target, the held-out reach)."""
    zero = torch.zeros(body.nv, dtype=common.F64)
    motions = [straight_reach(name, body, zero, p, DURATION)
               for name, p in targets(body, scales, turns).items()]
    return motions[:-1], motions[-1]


def _class(cfg: ExperimentConfig, body: Body) -> tuple:
    if cfg.quick:                         # two turns at one scale
        return reach_class(body, SCALES[:1], TURNS[1:3])
    return reach_class(body)


def run(cfg: ExperimentConfig) -> dict:
    """Per method (``cfg.methods``: the pipeline's search, the spanning layout) the basis
    learned on the class (its row, method NAME), and the held-out reach through it (method
    "NAME, held out")."""
    body = arm()
    train, held = _class(cfg, body)
    rows = []
    for method in cfg.methods:
        rows += _method_rows(cfg, body, method, train, held)
    return {"rows": rows, "summary": {"costs": common.costs(rows)}}


def _method_rows(cfg: ExperimentConfig, body: Body, method: str, train: list, held) -> list:
    """[the class's row, the held-out reach's row] of one method."""
    tcfg = cfg.training(method)
    learned = common.fit_pipeline_case(train, cfg, Path(cfg.out) / method / f"s{cfg.seed0}",
                                       cfg.seed0, method)
    lb = basis_io.load(learned["run"] / "basis.json")
    tg = prepare(body, [held])
    calls0, t0 = sim_mod.calls, time.perf_counter()
    weights = synthesize(lb, tg, tcfg.solver.shooting.options(phases=True),
                         cfg.simulation.options(), (cfg.success.rmse, cfg.success.tip),
                         ridge=tcfg.solver.ridge)
    fit = {"basis": lb.basis, "weights": weights, "wall": time.perf_counter() - t0,
           "sims": sim_mod.calls - calls0}
    m = common.check(body, lb.basis, weights, tg, cfg)
    row = common.row(f"{method}, held out", "held out", None, cfg.seed0, fit, m, tg.names)
    row["straightness_in"] = [straightness(body, held.q)]
    row["straightness_out"] = [straightness(body, m["q_sim"][0, :len(held.t)])]
    names = list(learned["metrics"]["motions"])
    basis_row = common.row(method, "class", None, cfg.seed0, learned,
                           common.pipeline_outcome(learned["metrics"], names), names)
    return [basis_row, row]


def _pairs(result: dict) -> list:
    """[(the class's row, the held-out reach's row)] per method."""
    rows = result["rows"]
    return list(zip(rows[::2], rows[1::2]))


def figures(cfg: ExperimentConfig, result: dict) -> list:
    """The held-out reach, input vs played through each method's basis, as stick figures
    and hand paths, beside each class reach against its reproductions."""
    body, fig_dir = arm(), common.figure_dir(cfg)
    train, held = _class(cfg, body)
    tg_held, tg = prepare(body, [held]), prepare(body, train)
    filtered, sims = {}, {}
    for base, row in _pairs(result):
        method = base["method"]
        filtered[method] = common.resimulate(body, row, tg_held, cfg)[0, :len(held.t)]
        sims[method] = common.pipeline_q(body, cfg, Path(cfg.out) / method / f"s{cfg.seed0}" / "run", tg)[0]
    out = draw(body, held, filtered, fig_dir, "input vs played through the class's fields")
    return out + common.sheets(body, tg, sims, fig_dir)


def summary(result: dict) -> str:
    """Per method, the class's own reproduction, and the held-out reach's distance to its
    input with both hand paths' deviation from their chords."""
    out = []
    for base, row in _pairs(result):
        worst = max(range(len(base["rmse"])), key=lambda k: base["rmse"][k])
        out.append(f"**{base['method']}**: basis learned on {len(base['motions'])} reaches: "
                   f"M = {base['M']}, {sum(base['success'])} of {len(base['success'])} reproduced "
                   f"(the worst, {base['motions'][worst]}: {base['rmse'][worst]:.4f} rad, "
                   f"{100 * base['tip'][worst]:.1f} cm).\n\n" + filtered_table(row, "held-out motion"))
    return "\n\n".join(out)


def goals(result: dict) -> list:
    """(goal, measured, met) per method: the class's reaches reproduced (the bar of every
    experiment), and the held-out reach within 0.05 rad of its input."""
    out = []
    for base, row in _pairs(result):
        name = base["method"]
        ok = sum(common.within_bar(r, p) for r, p in zip(base["rmse"], base["tip"]))
        out.append((f"{name}: every reach of the class with joint RMSE ≤ {common.BAR_RMSE:g} rad "
                    f"and tip error ≤ {100 * common.BAR_TIP:g} cm", f"{ok} of "
                    f"{len(base['success'])} within it; the worst RMSE {max(base['rmse']):.3f} "
                    f"rad, the worst tip error {100 * max(base['tip']):.1f} cm",
                    ok == len(base["success"])))
        worst = max(row["rmse"])
        out.append((f"{name}: the held-out reach, played through the class's frozen basis, "
                    f"within {GOAL_RMSE:g} rad joint RMSE of its input", f"{worst:.3f} rad",
                    worst <= GOAL_RMSE))
    return out
