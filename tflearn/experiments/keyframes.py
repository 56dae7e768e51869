"""Experiment 3 (thesis §4.3, figure 4-9): motions not made by torque fields.

For each gesture a three-keyframe eased spline through its postures at the start, the
middle and the end, and a straight-line reach of the hand (:mod:`tflearn.data.keyframes`);
each is learned by the ``pipeline`` (its own basis, M found), and all of them together
by the ``layout`` (one basis of fields spanning joint space around them, no search;
:mod:`tflearn.fit.layout`). The baseline is the
thesis' ``slsqp`` from the four generating fields of §4.2 (weights by NNLS), all
motions together. Goal: the bar of field-generated motions, joint RMSE ≤ 0.03 rad and
maximum hand-tip error ≤ 2 cm.
"""
from __future__ import annotations

from pathlib import Path

import torch

from ..data import gestures as gestures_mod
from ..data.keyframes import keyframe_motion, straight_reach
from ..fit import torque
from ..fit.targets import prepare
from ..physics import dynamics
from ..physics.body import Body, arm
from . import common
from .config import ExperimentConfig

TEXT = common.text("keyframes")
SHARED = ("come_here", "tuck", "backwards_reach")   # §4.2's four fields


def thesis() -> str:
    """The thesis' outcome, in words."""
    return TEXT["thesis"]


def keyframe_motions(body: Body, names: list, reach: bool = True) -> list:
    """§4.3's motions: for each gesture a three-keyframe eased spline through its postures
    at the start, the middle and the end, and (with ``reach``) a straight-line reach of
    the hand from rest to where the planar line ends."""
    source = common.gesture_motions(body, list(dict.fromkeys(names + ["planar_line"])))
    out = []
    for n in names:
        m = source[n]
        T = len(m.t)
        out.append(keyframe_motion(f"{n}_keys", body, m.q[[0, T // 2, T - 1]],
                                   [0.0, float(m.t[T // 2]), float(m.t[-1])]))
    if reach:
        end = dynamics.tip_position(body, source["planar_line"].q[-1])
        out.append(straight_reach("straight_reach", body, torch.zeros(body.nv, dtype=common.F64), end, 3.0))
    return out


def _slsqp_row(body: Body, tg, cfg: ExperimentConfig) -> dict:
    """The thesis' SLSQP from §4.2's four generating fields, weights by NNLS."""
    guess = common.generating([gestures_mod.GESTURES[g] for g in SHARED])
    zeros = torch.zeros(tg.N, 4, dtype=common.F64)
    basis, weights = common.build({**guess, "a": zeros, "b": zeros}, tg)
    torque.solve_weights(basis, weights, tg)
    with torch.no_grad():
        start = {"eta": basis.eta.clone(), "k": guess["k"], "a": weights.a.clone(), "b": weights.b.clone()}
    fit = common.fit_slsqp_case(body, start, tg, cfg)
    fit.pop("history")
    return common.row("slsqp", "keyframes", None, cfg.seed0, fit,
                      common.check(body, fit["basis"], fit["weights"], tg, cfg), tg.names)


def run(cfg: ExperimentConfig) -> dict:
    """Each keyframe motion learned by the pipeline alone, all of them by one layout, and
    the SLSQP baseline."""
    body = arm()
    motions = keyframe_motions(body, cfg.gestures, cfg.straight_reach)
    tg = prepare(body, motions)
    rows = [_slsqp_row(body, tg, cfg)] if "slsqp" in cfg.methods else []
    if "pipeline" in cfg.methods:
        for motion in motions:                         # each motion its own basis, M found
            fit = common.fit_pipeline_case([motion], cfg, Path(cfg.out) / "pipeline" / motion.name,
                                           cfg.seed0)
            rows.append(common.row("pipeline", motion.name, None, cfg.seed0, fit,
                                   common.pipeline_outcome(fit["metrics"], [motion.name]), [motion.name]))
    if "layout" in cfg.methods:                        # one basis for every motion, laid out
        fit = common.fit_pipeline_case(motions, cfg, Path(cfg.out) / "layout", cfg.seed0, "layout")
        rows.append(common.row("layout", "keyframes", None, cfg.seed0, fit,
                               common.pipeline_outcome(fit["metrics"], tg.names), tg.names))
    return {"rows": rows, "summary": {"costs": common.costs(rows)}}


def figures(cfg: ExperimentConfig, result: dict) -> list:
    """Per motion: target vs the SLSQP baseline vs its own pipeline run vs the shared
    layout, and the pipeline run's animation."""
    body, fig_dir = arm(), common.figure_dir(cfg)
    tg = prepare(body, keyframe_motions(body, cfg.gestures, cfg.straight_reach))
    sims, out = {}, []
    slsqp = next((x for x in result["rows"] if x["method"] == "slsqp"), None)
    if slsqp:
        sims["thesis SLSQP"] = common.resimulate(body, slsqp, tg, cfg)
    q = torch.full_like(tg.q, float("nan"))
    for j, name in enumerate(tg.names):
        run_dir = Path(cfg.out) / "pipeline" / name / "run"
        if (run_dir / "basis.json").exists():
            q[j] = common.pipeline_q(body, cfg, run_dir, tg.select([j]))[0][0]
            out += common.animations(run_dir, [name], fig_dir)
    if any(x["method"] == "pipeline" for x in result["rows"]):
        sims["pipeline"] = q
    if any(x["method"] == "layout" for x in result["rows"]):
        sims["layout"] = common.pipeline_q(body, cfg, Path(cfg.out) / "layout" / "run", tg)[0]
    return out + common.sheets(body, tg, sims, fig_dir)


def summary(result: dict) -> str:
    """Per method and motion: joint RMSE, tip error, the goal, M."""
    rows = [[x["method"], name, f"{x['rmse'][k]:.4f}", f"{100 * x['tip'][k]:.2f}",
             "yes" if common.within_bar(x["rmse"][k], x["tip"][k]) else "no", x.get("M", 4)]
            for x in result["rows"] for k, name in enumerate(x["motions"])]
    return common.table(["method", "motion", "joint RMSE (rad)", "tip error (cm)",
                         f"≤ {common.BAR_RMSE:g} rad and ≤ {100 * common.BAR_TIP:g} cm", "M"], rows)


def goals(result: dict) -> list:
    """(goal, measured, met): per method, every motion within joint RMSE ≤ 0.03 rad and
    maximum tip error ≤ 2 cm."""
    out = []
    for method in dict.fromkeys(x["method"] for x in result["rows"]):
        pairs = [(r, p) for x in result["rows"] if x["method"] == method
                 for r, p in zip(x["rmse"], x["tip"])]
        within = sum(common.within_bar(r, p) for r, p in pairs)
        out.append((f"{method}: every motion with joint RMSE ≤ {common.BAR_RMSE:g} rad and tip error "
                    f"≤ {100 * common.BAR_TIP:g} cm",
                    f"{within} of {len(pairs)} motions within it; the worst RMSE "
                    f"{max(r for r, _ in pairs):.3f} rad, the worst tip error "
                    f"{100 * max(p for _, p in pairs):.1f} cm", within == len(pairs)))
    return out
