"""Using a trained basis: re-simulate a run against motions, synthesise new motions with
a frozen basis, and play one motion's program from a ``basis.json``."""
from __future__ import annotations

import json
import math
from pathlib import Path

import torch

from . import config as config_mod
from .fields import FieldProgram, MotionWeights
from .fit import path as path_fit
from .fit.targets import Targets, prepare
from .fit.torque import solve_weights
from .io import basis as basis_io
from .motion import Motion, save as save_motion
from .simulate import simulate
from .train import check_resolution, load_motions, summarize


def synthesize(lb: basis_io.LearnedBasis, tg: Targets, path_steps: int = 20,
               lr: float = 0.003, **sim_kw) -> MotionWeights:
    """Held-out synthesis: with the basis frozen, fit new motions' weights by exact NNLS
    on their torques, then refine the weights alone by path matching."""
    z = torch.zeros(tg.N, lb.basis.M, dtype=torch.float64)
    weights = MotionWeights(z, z, tg.duration, names=tg.names)
    solve_weights(lb.basis, weights, tg)
    for p in lb.basis.parameters():
        p.requires_grad_(False)
    if path_steps:
        path_fit.path_match(lb.body, lb.basis, weights, tg, steps=path_steps, lr=lr,
                            fields=False, **sim_kw)
    return weights


def weights_for(lb: basis_io.LearnedBasis, tg: Targets):
    """The basis' weights for the motions of ``tg`` (by name); None where a name is new."""
    rows = [lb.names.index(n) if n in lb.names else None for n in tg.names]
    if any(r is None for r in rows):
        return None
    w = lb.weights
    idx = torch.as_tensor(rows)
    return MotionWeights(w.a[idx].detach(), w.b[idx].detach(), tg.duration,
                         w.step_onset[idx].detach(), w.step_duration[idx].detach(),
                         w.pulse_onset[idx].detach(), w.pulse_duration[idx].detach(),
                         names=tg.names)


def evaluate_run(run, data=None, out=None) -> dict:
    """Metrics of a run's basis.json on motions (default: the run's own data).

    Motions named in the basis are simulated with their stored weights; new ones are
    synthesised with the frozen basis (:func:`synthesize`). Writes RUN/evaluation.json
    (or ``out``) and returns its content."""
    run = Path(run)
    lb = basis_io.load(run / "basis.json")
    cfg = config_mod.load(run / "config.yaml") if (run / "config.yaml").exists() else config_mod.load()
    p = cfg["solver"]["path"]
    sim_kw = {"method": p["method"], "rtol": p["rtol"], "atol": p["atol"], "max_evals": p["max_evals"]}
    motions = load_motions(data if data is not None else cfg["data"], lb.body)
    resolution = dict(zip([m.name for m in motions], check_resolution(lb.body, motions)))
    known = [m for m in motions if m.name in lb.names]
    new = [m for m in motions if m.name not in lb.names]
    results, counts = {}, {}
    for group, synth in ((known, False), (new, True)):
        if not group:
            continue
        tg = prepare(lb.body, group)
        weights = synthesize(lb, tg, p["steps"], p["lr"], **sim_kw) if synth else weights_for(lb, tg)
        m = path_fit.metrics(lb.body, lb.basis, weights, tg, **sim_kw)
        ok = path_fit.succeeded(m, cfg["success"]["rmse"], cfg["success"]["tip"])
        s = summarize(m, ok, tg, lb.basis.M, 0.0)
        for j, (name, row) in enumerate(s["motions"].items()):
            row["synthesized"] = synth
            row["torque_resolution"] = resolution[name]
            results[name] = row
            counts[name] = int(tg.mask[j].sum())
    # Over all samples of all motions, as in metrics.json.
    n = sum(counts.values())
    overall = {"rmse": math.sqrt(sum(r["rmse"] ** 2 * counts[k] for k, r in results.items()) / n),
               "tip": max(r["tip"] for r in results.values()),
               "success": all(r["success"] for r in results.values()), "M": lb.basis.M}
    doc = {"motions": results, "overall": overall}
    Path(out or run / "evaluation.json").write_text(json.dumps(doc, indent=1))
    return doc


def simulate_basis_motion(basis_path, name: str, out, rate=None, duration=None) -> Path:
    """Play motion ``name``'s torque program from (q0, qd0) and write it as an .npz."""
    lb = basis_io.load(basis_path)
    j = lb.index(name)
    rate = float(rate or lb.rate[j])
    duration = float(duration or lb.weights.duration[j])
    t = torch.arange(0, int(round(duration * rate)) + 1, dtype=torch.float64) / rate
    with torch.no_grad():
        tr = simulate(lb.body, FieldProgram(lb.basis, lb.weights, index=[j]), lb.q0[j:j + 1],
                      lb.qd0[j:j + 1], t, rtol=1e-9, atol=1e-10)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    save_motion(Motion(name, t, tr.q[0], tr.v[0]), out)
    return out
