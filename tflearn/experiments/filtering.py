"""Experiment 4 (thesis §4.5.4, future work there): motion filtering.

A basis is learned on the gestures by the pipeline; crude motions (a straight-line
reach of the hand, a two-keyframe move) are then played through it: only their weights
are fitted (:func:`tflearn.evaluate.synthesize`: NNLS on the torques, then path
matching of the weights), and the simulation adds the fields' curvature, measured by
the hand path's deviation from its chord (:func:`straightness`).
"""
from __future__ import annotations

import math
import time
from pathlib import Path

import torch

from ..data.keyframes import keyframe_motion, straight_reach
from ..evaluate import synthesize
from ..fit.targets import prepare
from ..io import basis as basis_io
from ..physics import dynamics
from ..physics.body import Body, arm
from ..plots import figures as plots
from ..simulation import simulate as sim_mod
from . import common
from .config import ExperimentConfig

TEXT = common.text("filtering")


def thesis() -> str:
    """The thesis' outcome, in words."""
    return TEXT["thesis"]


def straightness(body: Body, q) -> float:
    """Largest distance of the hand path p(t) from its chord, relative to the chord's
    length: max_t ‖(p − p₀) − ((p − p₀)·u) u‖ / ‖p_T − p₀‖, u = (p_T − p₀)/‖p_T − p₀‖."""
    p = dynamics.tip_position(body, torch.as_tensor(q, dtype=common.F64))
    chord = p[-1] - p[0]
    u = chord / chord.norm()
    d = p - p[0]
    off = d - (d @ u)[:, None] * u
    return float(off.norm(dim=-1).max() / chord.norm())


def crude_motions(body: Body) -> list:
    """§4.5.4's crude inputs: a straight-line hand reach from rest to straight ahead (where
    the stiff-elbow lift ends) and a two-keyframe move from rest to the tuck's end posture."""
    src = common.gesture_motions(body, ["stiff_elbow_lift", "tuck"])
    zero = torch.zeros(body.nv, dtype=common.F64)
    reach = straight_reach("straight_reach", body, zero,
                           dynamics.tip_position(body, src["stiff_elbow_lift"].q[-1]), 3.0)
    move = keyframe_motion("two_key_move", body, torch.stack([zero, src["tuck"].q[-1]]), [0.0, 3.0])
    return [reach, move]


def run(cfg: ExperimentConfig) -> dict:
    """The basis learned on the gestures (its row), and the crude motions through it."""
    body = arm()
    learned = common.fit_pipeline_case(list(common.gesture_motions(body, cfg.gestures).values()),
                                       cfg, Path(cfg.out) / "pipeline" / f"s{cfg.seed0}", cfg.seed0)
    lb = basis_io.load(learned["run"] / "basis.json")
    motions = crude_motions(body)
    tg = prepare(body, motions)
    calls0, t0 = sim_mod.calls, time.perf_counter()
    weights = synthesize(lb, tg, cfg.train.solver.shooting.options(phases=False),
                         cfg.simulation.options(), (cfg.success.rmse, cfg.success.tip),
                         ridge=cfg.train.solver.ridge)
    fit = {"basis": lb.basis, "weights": weights, "wall": time.perf_counter() - t0,
           "sims": sim_mod.calls - calls0}
    m = common.check(body, lb.basis, weights, tg, cfg)
    row = common.row("filter", "crude", None, cfg.seed0, fit, m, tg.names)
    row["straightness_in"] = [straightness(body, x.q) for x in motions]
    row["straightness_out"] = [straightness(body, m["q_sim"][j, :len(x.t)]) for j, x in enumerate(motions)]
    names = list(learned["metrics"]["motions"])
    basis_row = common.row("pipeline", "gestures", None, cfg.seed0, learned,
                           common.pipeline_outcome(learned["metrics"], names), names)
    return {"rows": [basis_row, row], "summary": {"costs": common.costs([basis_row, row])}}


def figures(cfg: ExperimentConfig, result: dict) -> list:
    """Per crude motion: input vs filtered, as stick figures and hand paths."""
    body, fig_dir, out = arm(), common.figure_dir(cfg), []
    motions = crude_motions(body)
    q = common.resimulate(body, result["rows"][-1], prepare(body, motions), cfg)
    for j, m in enumerate(motions):
        out += draw(body, m, {"filtered": q[j, :len(m.t)]}, fig_dir,
                    "crude input vs played through the fields")
    return out


def draw(body: Body, motion, filtered: dict, fig_dir: Path, title: str) -> list:
    """NAME.png (stick figures) and NAME_hand.png (hand paths) of a motion, input against
    each filtered path of ``filtered`` (label → T×n)."""
    paths = {"input": motion.q, **filtered}
    strip, hand = fig_dir / f"{motion.name}.png", fig_dir / f"{motion.name}_hand.png"
    plots.save(plots.stick_strip(body, paths, title=f"{motion.name}: {title}"), strip)
    plots.save(plots.hand_paths(body, paths, title=f"{motion.name}: hand path"), hand)
    return [strip, hand]


def summary(result: dict) -> str:
    """The basis' own reproduction, and per crude motion the distance of the filtered
    motion to its input and both hand paths' deviation from their chords."""
    base, row = result["rows"]
    head = (f"Basis learned on {', '.join(base['motions'])}: M = {base['M']}, all "
            f"reproduced: {all(base['success'])}.")
    return head + "\n\n" + filtered_table(row, "crude motion")


def filtered_table(row: dict, what: str) -> str:
    """Per motion of a filter row: its distance to its input and both hand paths'
    deviation from their chords (``what`` names the motions' column)."""
    rows = [[name, f"{row['rmse'][k]:.4f}", f"{100 * row['tip'][k]:.1f}",
             _deviation(row["straightness_in"][k]), _deviation(row["straightness_out"][k])]
            for k, name in enumerate(row["motions"])]
    return common.table([what, "RMSE to input (rad)", "max tip distance to input (cm)",
                         "hand-path deviation from chord: input", "filtered"], rows)


def _deviation(x: float) -> str:
    """A hand path's deviation from its chord in %, or "–" for a path not simulated (NaN)."""
    return f"{100 * x:.1f}%" if math.isfinite(x) else "–"


def goals(result: dict) -> list:  # [(goal, measured, met)]
    """No goal is set for filtering (the thesis did not try it)."""
    return []
