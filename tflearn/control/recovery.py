"""The ``perturb`` command: push a limb driven by each controller and measure how it recovers.

For every motion of a :class:`tflearn.config.PerturbConfig` and every controller
(:mod:`tflearn.control.controllers`), the limb is simulated once unperturbed and once per
perturbation (each of ``pushes``, and the whole ``sweep`` — every impulse along every
direction — as one batched simulation), all from the target's initial state and sampled
at the target's times; :func:`tflearn.control.pushes.measure` gives the figures.

The target of motion NAME: the run's own data (its config.yaml's ``data``) when MODEL is
a run folder with a config, else NAME.npz beside the basis.json (as ``tflearn gestures``
writes them). MODEL may also be a folder of motions without a basis — NAME.npz with the
body in body.yaml, as ``tflearn bvh import`` writes recorded clips — for the tracking
controllers (``ff+pd``, ``ff``, ``pd-high``). The feed-forward torques are the target
spline's inverse dynamics on the body. ``fields`` plays the basis' program of NAME. A run
trained on moving torsos (``torso: moving``) is pushed on them: every controller's limb
rides the motion's torso (its feed-forward torques with the torso's inertial terms), and
the pushes' forces and the hand are in the torso's (chest's) frame.

Writes to ``out``: ``results.json`` (per motion and controller: the unperturbed tracking
RMSE and per case the push and its figures), ``figures/NAME_push.png`` (hand deviation
and hand paths of each controller for the first push, the push window marked),
``figures/NAME_sweep.png`` (largest hand deviation against impulse), with ``animation``
``figures/NAME.gif`` (the controllers side by side under the first push), with
``tensorboard`` ``tensorboard/`` (scalars ``perturb/NAME/CONTROLLER/FIGURE`` by case and
the figures).
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

import numpy as np

from ..config import PerturbConfig
from ..errors import InputError
from ..io import basis as basis_io
from ..io.files import write_text
from ..model.program import FieldProgram
from ..simulation.simulate import SimOptions
from . import controllers as C
from . import pushes as P


def targets(model, names: list) -> tuple:
    """(body, LearnedBasis or None, {name: target Motion}, {name: its torso, a one-member
    :class:`tflearn.motions.torso.Bases`, or None}) of a MODEL: a run folder or its
    basis.json (the basis' body and program; the torsos of a run with ``torso: moving``),
    or a folder of motions without a basis, as ``tflearn bvh import`` writes them
    (NAME.npz and body.yaml, the performer's arm), for the tracking controllers only, on
    a fixed base. Raises :class:`InputError` naming a motion the basis or the data does
    not hold."""
    model = Path(model)
    if model.is_dir() and not (model / "basis.json").exists():
        from ..config import read_body
        if not (model / "body.yaml").exists():
            raise InputError(f"{model}: neither a run (no basis.json) nor a folder of imported "
                             f"motions (no body.yaml)")
        body = read_body(model / "body.yaml")
        return body, None, _beside(model, names, body), dict.fromkeys(names)
    from ..data.loading import named_motions, torsos
    from ..evaluate import run_config
    run, path = (model, model / "basis.json") if model.is_dir() else (model.parent, model)
    lb = basis_io.load(path)
    for name in names:
        lb.index(name)
    if not (run / "config.yaml").exists():
        return lb.body, lb, _beside(path.parent, names, lb.body, f"{path}: "), dict.fromkeys(names)
    cfg, _ = run_config(run)
    motions = named_motions(cfg.data, lb.body, names, str(path))
    bases = torsos(cfg.data, motions, cfg.torso)
    return (lb.body, lb, dict(zip(names, motions)),
            {n: None if bases is None else bases.take([j]) for j, n in enumerate(names)})


def _beside(folder: Path, names: list, body, where: str = "") -> dict:
    """{name: folder/NAME.npz} loaded on ``body``; InputError naming a missing one."""
    from ..motions.motion import load as load_motion
    found = {}
    for name in names:
        npz = folder / f"{name}.npz"
        if not npz.exists():
            raise InputError(f"{where}no target for motion {name!r} (no {npz})")
        found[name] = load_motion(npz, body)
    return found


def _cases(cfg: PerturbConfig) -> list:
    """[(label, Perturbation, impulses (B×3) or None)]: each push alone, then the sweep."""
    cases = []
    for p in cfg.pushes:
        push = P.Push(tuple(p.force), p.at, p.duration, p.point)
        cases.append((f"push {tuple(p.force)} N at {p.at:g} s", P.Perturbation((push,), cfg.carry), None))
    s = cfg.sweep
    if s.directions and s.impulses:
        dirs = np.asarray(s.directions, dtype=float)
        dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
        J = np.concatenate([dirs * j for j in s.impulses])          # impulse-major
        push = P.Push.from_impulse(J, s.at, s.duration, s.point)
        cases.append(("sweep", P.Perturbation((push,), cfg.carry), J))
    if not cases:
        cases.append(("carry", P.Perturbation((), cfg.carry), None))
    return cases


def _select(r: P.Response, i: int) -> P.Response:
    return P.Response(r.t, r.q[i], r.v[i], r.tau[i], r.hand[i], r.push_work[i], r.work[i])


def _push_doc(case: P.Perturbation, i: int) -> dict:
    push = case.pushes[0] if case.pushes else None
    if push is None:
        return {"carry_kg": case.carry}
    F = np.asarray(push.force, dtype=float).reshape(-1, 3)[i]
    return {"force": F.tolist(), "impulse": (F * push.duration / 2).tolist(),
            "impulse_Ns": float(np.linalg.norm(F) * push.duration / 2), "at": push.onset,
            "duration": push.duration, "point": push.point, "carry_kg": case.carry}


def run_motion(body, lb, motion, cfg: PerturbConfig, options: SimOptions,
               done: Callable[[str], None] = lambda what: None, base=None) -> dict:
    """Every controller × case on one motion: {controller: {"rmse", "cases": [...]}} and the
    responses {controller: (unperturbed, [pushed per case])} for the figures. ``lb``: the
    learned basis (for ``fields``), or None; ``base``: the motion's torso (a one-member
    :class:`tflearn.motions.torso.Bases`) or None (fixed). ``done(what)`` follows each
    simulation, 1 + len(cases) per controller ("CONTROLLER: CASE")."""
    program = None
    if lb is not None:
        program = FieldProgram(lb.basis, lb.weights.select_motions([lb.index(motion.name)]))
    target = C.Target(body, motion, base=base)
    copts = C.ControllerOptions(scale=cfg.gains.scale, bilinear=cfg.gains.bilinear,
                                high_gain=cfg.gains.high_gain)
    q0, v0, _ = target(motion.t[0])
    cases = _cases(cfg)
    doc, responses = {}, {}
    for name in cfg.controllers:
        ctrl = C.build(name, target, program, copts)
        still = _select(P.respond(body, ctrl, P.Perturbation(), q0[None], v0[None], motion.t, options,
                                  base), 0)
        done(f"{name}: unperturbed")
        rows, pushed = [], []
        for label, case, J in cases:
            B = 1 if J is None else len(J)
            r = P.respond(body, ctrl, case, q0.expand(B, -1), v0.expand(B, -1), motion.t, options, base)
            done(f"{name}: {label}")
            pushed.append(r)
            for i in range(B):
                row = {"case": label, **_push_doc(case, i)}
                row.update(P.measure(case.body(body), still, _select(r, i), motion.q, case.window(), cfg.tol))
                rows.append(row)
        doc[name] = {"rmse": P.tracking_rmse(body, still, motion.q), "cases": rows}
        responses[name] = (still, pushed)
    return doc, responses, cases


def run(cfg: PerturbConfig, progress: bool = True) -> dict:
    """Run the config; returns the content of OUT/results.json (see the module).
    ``progress``: a bar on stderr (:func:`tflearn.log.progress_bar`) counting the
    simulations and each motion's figures."""
    from ..log import RunLog, progress_bar
    out = Path(cfg.out)
    body, lb, motions, bases = targets(cfg.model, cfg.motions)
    if lb is None and "fields" in cfg.controllers:
        raise InputError(f"{cfg.model}: no basis.json, so there is no 'fields' controller to "
                         f"push (choose among {', '.join(c for c in C.CONTROLLERS if c != 'fields')})")
    for _, case, _ in _cases(cfg):               # unknown points refused before any work
        for push in case.pushes:
            P.point_on(body, push.point)
    (out / "figures").mkdir(parents=True, exist_ok=True)
    options = cfg.simulation.options()
    doc = {"model": cfg.model, "config": cfg.model_dump(), "gains": {
        k: {"K": v[0], "B": v[1]} for k, v in C.HUMAN_ARM_GAINS.items()}, "motions": {},
        "units": {"max_joint_dev": "rad", "max_hand_dev": "m", "recovery_s": "s (null: not recovered)",
                  "final_joint_error": "rad", "final_hand_error": "m", "peak_torque": "N m",
                  "push_work": "J", "impulse_Ns": "N s", "rmse": "rad"}}
    steps = len(motions) * (len(cfg.controllers) * (1 + len(_cases(cfg))) + 1)
    with RunLog(out, tensorboard=cfg.tensorboard, progress=False) as rl, \
            progress_bar(steps, "perturb", "steps", progress) as bar:
        rl.open()
        for name, motion in motions.items():
            def done(what: str, name=name) -> None:
                bar.set_postfix_str(f"{name}: {what}", refresh=False)
                bar.update()
            res, responses, cases = run_motion(body, lb, motion, cfg, options, done, bases[name])
            doc["motions"][name] = res
            for c, r in res.items():
                for k, row in enumerate(r["cases"]):
                    for key in ("max_hand_dev", "max_joint_dev", "peak_torque", "final_joint_error"):
                        rl.scalar(f"perturb/{name}/{c}/{key}", row[key], k)
            bar.set_postfix_str(f"{name}: figures" + (" and animation" if cfg.animation else ""))
            _figures(body, name, motion, res, responses, cases, cfg, out, rl)
            bar.update()
    write_text(out / "results.json", json.dumps(doc, indent=1))
    return doc


def _figures(body, name, motion, res, responses, cases, cfg, out, rl) -> None:
    """The push figure and the animation of the first case, the sweep figure."""
    from ..plots import figures as plots
    from ..plots.recovery import deviation_sweep, push_response
    label, case, J = cases[0]
    base = {c: b.q for c, (b, _) in responses.items()}
    pushed = {c: p[0].q[0] for c, (_, p) in responses.items()}
    window = case.window()
    title = f"{name}: {label}" if J is None else f"{name}: {float(np.linalg.norm(J[0])):.3g} N·s push"
    fig = push_response(case.body(body), motion.t, base, pushed, window, cfg.tol, title)
    rl.figure(f"perturb/{name}/push", fig, 0)
    plots.save(fig, out / "figures" / f"{name}_push.png")
    if cases[-1][0] == "sweep":
        push = cases[-1][1].pushes[0]
        rows = {c: [row for row in r["cases"] if row["case"] == "sweep"] for c, r in res.items()}
        fig = deviation_sweep(rows, title=f"{name}: largest hand deviation against impulse "
                                          f"({push.point}, {push.duration:g} s pulse)")
        rl.figure(f"perturb/{name}/sweep", fig, 0)
        plots.save(fig, out / "figures" / f"{name}_sweep.png")
    if cfg.animation:
        from ..render import frame_samples, write_gif
        t = motion.t.numpy()
        paths = {c: plots.joint_positions(case.body(body), q) for c, q in pushed.items()}
        write_gif(paths, t, frame_samples(t, 25), 25, out / "figures" / f"{name}.gif", title,
                  keep=False, reference=plots.joint_positions(body, motion.q), window=window)


def summary_lines(doc: dict) -> list:
    """One line per motion × controller × case for the terminal."""
    lines = []
    for name, res in doc["motions"].items():
        for c, r in res.items():
            for row in r["cases"]:
                rec = "not recovered" if row["recovery_s"] is None else f"recovered {row['recovery_s']:.2f} s"
                imp = f"{row['impulse_Ns']:.3g} N·s" if "impulse_Ns" in row else f"carry {row['carry_kg']} kg"
                lines.append(f"{name:>18s} {c:>8s} {imp:>10s}: max hand dev "
                             f"{100 * row['max_hand_dev']:6.2f} cm, {rec}, final error "
                             f"{row['final_joint_error']:.3f} rad, peak torque {row['peak_torque']:.2f} N·m")
    return lines

