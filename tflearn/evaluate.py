"""Using a trained basis: re-simulate a run against motions, synthesise new motions with
a frozen basis, and play one motion's program from a ``basis.json``."""
from __future__ import annotations

import json
import warnings
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import Optional, Sequence

import torch

from . import config as config_mod
from . import synthesis
from .config import Config
from .data.loading import check_resolution, load_motions, named_motions, torsos
from .fit import impedance, stability
from .fit.shooting import ShootingOptions
from .fit.targets import Targets, prepare, submovement_windows
from .fit.torque import DivergenceWarning
from .io import basis as basis_io
from .io.basis import LearnedBasis
from .io.files import write_text
from .log import progress_bar
from .metrics import UNITS, numbers, pooled_rmse, score, summarize
from .mocap.clips import import_like
from .model.program import FieldProgram
from .model.weights import MotionWeights
from .motions.motion import Motion
from .motions.motion import save as save_motion
from .simulation.simulate import SimOptions, simulate


def run_config(run) -> tuple:
    """(config, simulation options) of a run folder: its config.yaml, or the defaults."""
    path = Path(run) / "config.yaml"
    cfg = config_mod.load(path) if path.exists() else Config()
    return cfg, cfg.solver.path.options()


def synthesize(lb: basis_io.LearnedBasis, tg: Targets,
               shooting: Optional[ShootingOptions] = ShootingOptions(),
               options: SimOptions = SimOptions(), success: tuple = (0.03, 0.02), *,
               ridge: float = 0.0, held: impedance.Impedance = impedance.Impedance(),
               window_rate: float = 0.0, ladder: Sequence[tuple] = (), finer: int = 0) -> MotionWeights:
    """Held-out synthesis (:mod:`tflearn.synthesis`): with the basis frozen, fit new
    motions' weights by NNLS on their torques (exact, or with a ``ridge``:
    :func:`~tflearn.fit.torque.solve_weights`; with ``held``, also on the stiffness about
    the path that a run of ``solver.layout.frequency`` asked: :mod:`tflearn.fit.impedance`);
    the motions that this does not reproduce
    (joint RMSE ≤ ``success[0]`` rad and hand-tip error ≤ ``success[1]`` m, as in
    training) then get their weights (and with ``shooting.phases`` their activation
    timing) by multiple-shooting path matching (None: NNLS only). A motion that is still
    not reproduced is fitted again by shooting from the basis' own program whose torques
    match it best (:func:`~tflearn.synthesis.nearest_programs`), and keeps whichever
    of the two fits, or that program as it is, simulates closest to it (joint RMSE; one
    that cannot be simulated is farthest); where the kept fit's shooting stopped early, a
    :class:`~tflearn.fit.torque.DivergenceWarning` names the motion and why. The new
    motions get as many sub-movement windows as the basis' own motions have, placed from
    their data (:func:`submovement_windows`; with a ``window_rate``, as many as their
    length asks, up to that many). ``ladder``: further (window rate, impedance) settings
    that the motions the NNLS leaves unreproduced try in turn before shooting
    (:func:`~tflearn.synthesis.held_ladder`: a held run's ``solver.hold.settings()`` after
    its first, as training held its own motions). ``finer``: a motion still not reproduced
    is cut into ``window_rate`` × 2ᵏ windows a second, k = 1 … ``finer``, and shot again,
    keeping the closer program (:func:`~tflearn.synthesis.finer`, as training's
    ``model.finer``; the windows up to the run's P)."""
    weights = MotionWeights.zeros(lb.basis.M, tg.duration, tg.names,
                                  submovement_windows(tg, lb.weights.P, rate=window_rate))
    if ladder:
        def judge(sub, part):
            s = score(lb.body, lb.basis, sub, part, options)
            return s.failure, s.succeeded(*success)
        synthesis.held_ladder(lb.body, lb.basis, weights, tg, [(window_rate, held), *ladder], judge, ridge)
    else:
        impedance.solve_weights(lb.body, lb.basis, weights, tg, held, ridge=ridge)
    if shooting is None or not shooting.iterations:
        return weights
    nearest = partial(synthesis.nearest_programs, lb.basis, lb.weights)
    failures = synthesis.fit_programs(lb.body, lb.basis, weights, tg, shooting, options, success, nearest)
    if finer and window_rate:
        kept = _finer(lb, weights, tg, shooting, options, success, held, ridge,
                      [window_rate * 2 ** k for k in range(1, finer + 1)])
        failures = {name: why for name, why in failures.items() if tg.names.index(name) not in kept}
    for name, why in failures.items():
        warnings.warn(f"synthesis of {name}: multiple shooting stopped: {why}", DivergenceWarning,
                      stacklevel=2)
    return weights


def _finer(lb: basis_io.LearnedBasis, weights: MotionWeights, tg: Targets, shooting: ShootingOptions,
           options: SimOptions, success: tuple, held: impedance.Impedance, ridge: float, rates: list) -> dict:
    """:func:`synthesize`'s finer windows (``rates`` a second in turn) for the motions its
    fits leave unreproduced; {motion index: the rate it kept}."""
    todo, far = synthesis.unreproduced(lb.body, lb.basis, weights, tg, options, success, range(tg.N))

    def shoot(sub, part):
        synthesis.shoot(lb.body, lb.basis, sub, part, list(range(part.N)), shooting, options)

    def judge(sub, part):
        s = score(lb.body, lb.basis, sub, part, options)
        return s, s.succeeded(*success)
    return synthesis.finer(lb.body, lb.basis, weights, tg, dict(zip(todo, far)), rates, held, shoot, judge,
                           success, ridge)


def weights_for(lb: basis_io.LearnedBasis, tg: Targets) -> MotionWeights:
    """The basis' weights for the motions of ``tg`` (by name, each with its own
    duration); raises :class:`~tflearn.errors.InputError` naming a motion the basis does not hold."""
    rows = [lb.index(n) for n in tg.names]
    w = lb.weights.select_motions(rows)
    w.duration.copy_(tg.duration)
    return w


def evaluate_run(run, data=None, out=None, progress: bool = True, simulation: Optional[dict] = None) -> dict:
    """Metrics of a run's basis.json on motions (default: the run's own data).

    Motions named in the basis are simulated with their stored weights; new ones are
    synthesised with the frozen basis (:func:`synthesize`), one at a time, under a
    progress bar (``progress``). ``data`` may name BVH clips: they are imported into
    OUT's folder/imported in the run's body and chart with its ``bvh`` choices
    (:func:`tflearn.mocap.clips.import_like`; a folder of motions in another body is
    refused). Writes ``out`` (default RUN/evaluation.json) after each synthesised motion,
    with ``"complete"`` false until the last, and beside it the folder synthesized/: a run
    folder of the new motions (basis.json of the fields and their programs, config.yaml
    naming their data), which ``tflearn simulate``, ``render`` and ``perturb`` take as
    RUN. ``simulation``: settings of the run's :class:`SimOptions` replaced (``rtol``,
    ``atol``, ``max_evals``: whether a reproduction holds at tighter tolerances),
    recorded with the others in the file's ``"simulation"``. Returns the metrics."""
    run = Path(run)
    lb = basis_io.load(run / "basis.json")
    cfg, options = run_config(run)
    options = replace(options, **(simulation or {}))
    used = {k: getattr(options, k) for k in ("method", "rtol", "atol", "max_evals")}
    out = Path(out or run / "evaluation.json")
    source = cfg.data if data is None else (import_like(cfg, data, out.parent / "imported") or data)
    motions = load_motions(source, lb.body, strict=cfg.strict)
    resolution = dict(zip([m.name for m in motions], check_resolution(lb.body, motions)))
    known = [m for m in motions if m.name in lb.names]
    new = [m for m in motions if m.name not in lb.names]
    results, counts = {}, {}
    shoot = cfg.solver.shooting.options(cfg.model.phases == "variable")
    rate, held, ladder = _asked(run, cfg)

    def scored(group: list, synth: bool) -> LearnedBasis:
        tg = prepare(lb.body, group, weight=cfg.solver.torque_weight,   # the run's cost and torso
                     base=torsos(source, group, cfg.torso))
        weights = (synthesize(lb, tg, shoot, options, (cfg.success.rmse, cfg.success.tip),
                              ridge=cfg.solver.ridge, held=held, window_rate=rate, ladder=ladder,
                              finer=cfg.model.finer) if synth
                   else weights_for(lb, tg))
        s = score(lb.body, lb.basis, weights, tg, options)
        ok = s.succeeded(cfg.success.rmse, cfg.success.tip)
        summary = summarize(s, ok, tg, lb.basis.M, 0.0, stability.growth(lb.body, lb.basis, weights, tg),
                            impedance.path_stiffness(lb.body, lb.basis, weights, tg),
                            numbers(weights, tg, lb.body.nv))
        for j, (name, row) in enumerate(summary["motions"].items()):
            results[name] = {**row, "synthesized": synth, "torque_resolution": resolution[name]}
            counts[name] = int(tg.mask[j].sum())
        return LearnedBasis(lb.body, lb.basis, weights, tg.q0, tg.qd0, tg.rate)

    if known:
        scored(known, False)
    if not new:
        return _write(out, results, counts, lb.basis.M, used, complete=True)
    programs, synth = [], out.parent / "synthesized"
    synth.mkdir(parents=True, exist_ok=True)
    config_mod.dump(cfg.replace(data=_absolute(source), out=str(synth)), synth / "config.yaml")
    with progress_bar(len(new), "synthesis", "motions", progress) as bar:
        for m in new:
            programs.append(scored([m], True))
            r = results[m.name]
            bar.set_postfix_str(f"{m.name}: {r['rmse']:.4f} rad, {100 * r['tip']:.2f} cm")
            bar.update()
            doc = _write(out, results, counts, lb.basis.M, used, complete=len(programs) == len(new))
            basis_io.save(_joined(programs), synth / "basis.json")
    return doc


def _asked(run: Path, cfg) -> tuple:
    """(window rate, impedance, ladder) with which a run's new motions are synthesised:
    a layout run's stiffness about the path; a run whose held model was kept
    (metrics.json's ``history.hold.kept``) its ``solver.hold.settings()`` in turn; else
    torques alone."""
    if cfg.solver.method == "layout":
        return cfg.model.window_rate, cfg.solver.layout.impedance(), []
    metrics = run / "metrics.json"
    hold = json.loads(metrics.read_text()).get("history", {}).get("hold") if metrics.exists() else None
    if hold and hold.get("kept"):
        (rate, held), *ladder = cfg.solver.hold.settings()
        return rate, held, ladder
    return cfg.model.window_rate, impedance.Impedance(), []


def _absolute(data):
    """A config's ``data`` with its paths made absolute (the built-in "gestures" as it is)."""
    if isinstance(data, (str, Path)):
        return data if str(data) == "gestures" else str(Path(data).resolve())
    return [str(Path(p).resolve()) for p in data]


def _joined(parts: list) -> LearnedBasis:
    """One basis file's content from programs on the same fields."""
    weights = MotionWeights.concat([p.weights for p in parts])
    q0, qd0, rate = (torch.cat([getattr(p, k) for p in parts]) for k in ("q0", "qd0", "rate"))
    return LearnedBasis(parts[0].body, parts[0].basis, weights, q0, qd0, rate)


def _write(out: Path, results: dict, counts: dict, M: int, simulation: dict, complete: bool) -> dict:
    """Write the evaluation so far (over all samples of all motions, as in metrics.json;
    ``simulation``: how the motions were simulated)."""
    overall = {"rmse": pooled_rmse([r["rmse"] for r in results.values()], list(counts.values())),
               "tip": max(r["tip"] for r in results.values()),
               "numbers_per_s": max(r["numbers_per_s"] for r in results.values()),
               "success": all(r["success"] for r in results.values()), "M": M}
    doc = {"motions": results, "overall": overall, "units": dict(UNITS), "simulation": simulation,
           "complete": complete}
    write_text(out, json.dumps(doc, indent=1))
    return doc


def simulate_basis_motion(basis_path, name: str, out, rate=None, duration=None) -> Path:
    """Play motion ``name``'s torque program from (q0, qd0) and write it as an .npz; on
    its torso when the basis is a run's whose config says ``torso: moving``."""
    lb = basis_io.load(basis_path)
    j = lb.index(name)
    rate = float(rate or lb.rate[j])
    duration = float(duration or lb.weights.duration[j])
    t = torch.arange(0, int(round(duration * rate)) + 1, dtype=torch.float64) / rate
    base, run = None, Path(basis_path).parent
    cfg = run_config(run)[0] if (run / "config.yaml").exists() else None
    if cfg is not None and cfg.torso == "moving":     # its torso file beside the run's data
        found = named_motions(cfg.data, lb.body, [name], f"{basis_path} (torso: moving)")
        base = torsos(cfg.data, found, cfg.torso)
    with torch.no_grad():
        tr = simulate(lb.body, FieldProgram(lb.basis, lb.weights, index=[j]), lb.q0[j:j + 1],
                      lb.qd0[j:j + 1], t, SimOptions(rtol=1e-9, atol=1e-10, max_evals=None), base=base)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    save_motion(Motion(name, t, tr.q[0], tr.v[0]), out)
    return out
