"""The ``tflearn modes CONFIG`` command: analyse, animate, draw and log a body's modes.

Writes into ``out`` (the config's, or ``--out``):

* ``modes.json`` — format ``tflearn-modes/1``: the body (:meth:`Body.to_dict`), the rest
  pose, chart, floating flag, joint stiffness (nv×nv) and constraints used, and per mode
  its index, frequency (Hz), rigid flag and shape (nx, M-orthonormal, in the chart);
* ``mode_II.npz`` — each of the lowest ``animation.modes`` non-rigid modes alone,
  θ₀ ⊕ α û sin(2π f t) with û the shape scaled to a largest joint coordinate of 1
  (:func:`tflearn.modes.motion.unit_shapes`) and α = ``animation.amplitude`` rad
  (Motion format, :mod:`tflearn.motions.motion`; the joints only, a floating base's motion is
  in the pictures but not in the .npz);
* ``mode_II.bvh`` — the same, for a body from a BVH skeleton (``skeleton``), in that
  file's hierarchy, playable in any BVH viewer;
* ``mode_II.png`` — its stick figures at −α, 0 and +α (a floating base moved too);
* ``motion.npz`` (and ``motion_pd.npz``, the PD-driven simulation, for a fixed base) when
  ``motion.drives`` is given; ``following`` in modes.json says how closely it followed;
* ``tensorboard/`` — ``modes/frequency_hz`` (step = mode index) and the shape figures.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from ..io.files import write_text
from ..motions.motion import Motion
from ..motions.motion import save as save_motion
from ..physics.body import from_config
from . import analysis as md
from . import motion as mm
from .config import ModesConfig

FORMAT = "tflearn-modes/1"


def skeleton_of(cfg: ModesConfig):
    """The BVH skeleton of a config's ``skeleton`` section (None without one)."""
    if cfg.skeleton is None:
        return None
    from ..mocap.bvh import read
    return read(cfg.skeleton.file, scale=cfg.skeleton.scale)


def constraints_of(cfg: ModesConfig) -> list:
    """The config's constraints (:class:`tflearn.modes.analysis.Constraint`)."""
    return [md.Constraint.from_config(c.model_dump(), f"constraints[{k}]")
            for k, c in enumerate(cfg.constraints)]


def drives_of(cfg: ModesConfig) -> list:
    """The config's ``motion.drives`` (:class:`tflearn.modes.motion.ModeDrive`)."""
    return [mm.ModeDrive(**d.model_dump()) for d in cfg.motion.drives]


def analyse_config(cfg: ModesConfig, skel=None) -> md.Modes:
    """The modes a config describes (``skel``: its skeleton, if already read)."""
    skel = skel if skel is not None else skeleton_of(cfg)
    if skel is not None:
        from ..mocap.skeleton import body_from_skeleton
        body = body_from_skeleton(skel, cfg.skeleton.mass)
    else:
        body = from_config(cfg.body)
    s = cfg.stiffness
    K = md.stiffness_matrix(body, s.uniform, s.scale, s.matrix)
    return md.analyse(body, md.rest_pose(body, cfg.pose), K, constraints_of(cfg),
                      md.ModalOptions(chart=cfg.chart, floating=cfg.floating))


def animated_modes(modes: md.Modes, count: int) -> list:
    """Indices of the lowest ``count`` non-rigid modes."""
    return [int(i) for i in np.nonzero(~modes.rigid)[0][:count]]


def mode_motion(modes: md.Modes, i: int, amplitude: float, periods: float, samples: int):
    """Mode i alone as a Motion: its largest joint excursion is ``amplitude`` rad."""
    f = float(modes.frequencies[i])
    n = max(4, int(round(periods * samples)) + 1)
    t = np.linspace(0.0, periods / f, n)
    q = mm.kinematic(modes, [mm.ModeDrive(i, amplitude=amplitude)], t)
    return Motion(f"mode_{i:02d}", t, q, body=modes.body)


def write_bvh(skel, body, motion: Motion, path) -> None:
    """A motion of a skeleton's body as BVH in the skeleton's own hierarchy and channel
    orders (the root held at its first frame's position, unrotated)."""
    from ..mocap import bvh
    from ..mocap.skeleton import rotations
    F = motion.T
    R = rotations(skel, body, motion.q.numpy())
    P = np.broadcast_to(skel.positions[:1], (F,) + skel.positions.shape[1:])
    bvh.write(skel, path, bvh.channel_values(skel, R, P),
              frame_time=float(motion.t[1] - motion.t[0]))


def base_pose(floating: bool, x: np.ndarray):
    """(R, p) of a floating base displaced by x (its first six coordinates: R = exp([x_ω]×),
    p = x_v), None for a fixed base."""
    if not floating:
        return None
    from ..physics.configspace import rotvec_to_rotmat
    return rotvec_to_rotmat(torch.as_tensor(x[3:md.N_BASE])).numpy(), x[:3]


def table(modes: md.Modes, rows: int) -> str:
    """The lowest frequencies as a text table."""
    lines = [f"{'mode':>4s}  {'f (Hz)':>10s}  {'ω (rad/s)':>10s}  kind"]
    for i in range(min(rows, modes.frequencies.size)):
        f = modes.frequencies[i]
        kind = "rigid" if modes.rigid[i] else ""
        lines.append(f"{i:4d}  {f:10.4f}  {2 * np.pi * f:10.4f}  {kind}")
    return "\n".join(lines)


def document(cfg: ModesConfig, modes: md.Modes, following=None) -> dict:
    """The modes.json document."""
    K = modes.K[md.N_BASE:, md.N_BASE:] if modes.options.floating else modes.K
    return {"format": FORMAT, "body": modes.body.to_dict(), "pose": modes.q0.tolist(),
            "chart": modes.options.chart, "floating": modes.options.floating,
            "stiffness": K.tolist(),
            "constraints": [c.model_dump() for c in cfg.constraints],
            "coordinates": (["base v x", "base v y", "base v z", "base ω x", "base ω y",
                             "base ω z"] if modes.options.floating else [])
            + md.joint_names(modes.body),
            "modes": [{"index": i, "frequency_hz": float(modes.frequencies[i]),
                       "rigid": bool(modes.rigid[i]), "shape": modes.shapes[:, i].tolist()}
                      for i in range(modes.frequencies.size)],
            "following": following}


def run(cfg: ModesConfig, out=None, progress: bool = True) -> dict:
    """Analyse, write everything listed in the module into ``out`` (default cfg.out) and
    return {"modes": Modes, "out": Path, "written": [paths], "following": dict | None}.
    ``progress``: after the analysis, a bar on stderr (:func:`tflearn.log.progress_bar`)
    over the steps: each animated mode, the combined motion, TensorBoard, each figure."""
    from ..log import progress_bar
    from ..plots import bodies
    from ..plots import figures as plots
    out = Path(out if out is not None else cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    skel = skeleton_of(cfg)
    modes = analyse_config(cfg, skel)
    written, figures = [], {}
    a = cfg.animation
    unit = mm.unit_shapes(modes)[0]
    animated = animated_modes(modes, a.modes)
    with progress_bar(2 * len(animated) + bool(cfg.motion.drives) + cfg.log.tensorboard, "modes",
                      "steps", progress) as bar:
        for i in animated:
            bar.set_postfix_str(f"mode {i}")
            motion = mode_motion(modes, i, a.amplitude, a.periods, a.samples)
            save_motion(motion, out / f"{motion.name}.npz")
            if skel is not None:
                write_bvh(skel, modes.body, motion, out / f"{motion.name}.bvh")
                written.append(out / f"{motion.name}.bvh")
            poses = {"rest": (modes.q0, None)}
            for sign, label in ((-1, "−α"), (1, "+α")):
                x = sign * a.amplitude * unit[:, i]
                poses[label] = (mm.retract(modes, torch.as_tensor(x[-modes.body.nv:])).numpy(),
                                base_pose(modes.options.floating, x))
            fig = bodies.mode_shape(modes.body, poses, f"{modes.body.name}: mode {i}, "
                                    f"{modes.frequencies[i]:.3f} Hz (α = {a.amplitude} rad)")
            figures[i] = fig
            written += [out / f"{motion.name}.npz", out / f"{motion.name}.png"]
            bar.update()
        bar.set_postfix_str("combined motion" + (" and PD follow" if cfg.motion.dynamic else ""))
        following = _combined_motion(cfg, modes, out, written)
        bar.update(bool(cfg.motion.drives))
        write_text(out / "modes.json", json.dumps(document(cfg, modes, following), indent=1))
        written.insert(0, out / "modes.json")
        if cfg.log.tensorboard:
            bar.set_postfix_str("TensorBoard")
            _log(cfg, modes, out, figures)
            bar.update()
        for i, fig in figures.items():
            bar.set_postfix_str(f"mode_{i:02d}.png")
            plots.save(fig, out / f"mode_{i:02d}.png")
            bar.update()
    return {"modes": modes, "out": out, "written": written, "following": following}


def _combined_motion(cfg: ModesConfig, modes: md.Modes, out: Path, written: list):
    """motion.npz (and the PD follow) of ``motion.drives``; the following summary."""
    m = cfg.motion
    if not m.drives:
        return None
    drives = drives_of(cfg)
    limits = mm.Limits.from_config(modes.body, m.limits, m.soft)
    t = np.linspace(0.0, m.duration, max(4, int(round(m.duration * m.rate)) + 1))
    q = mm.kinematic(modes, drives, t, limits)
    save_motion(Motion("motion", t, q, body=modes.body), out / "motion.npz")
    written.append(out / "motion.npz")
    if not m.dynamic or modes.options.floating:
        return None
    fol = mm.follow(modes, drives, t, limits, m.damping)
    save_motion(Motion("motion_pd", t, fol.trajectory.q, body=modes.body), out / "motion_pd.npz")
    written.append(out / "motion_pd.npz")
    return {"rms_rad": fol.rms, "max_rad": fol.max, "damping": m.damping}


def _log(cfg: ModesConfig, modes: md.Modes, out: Path, figures: dict) -> None:
    if not cfg.log.tensorboard:
        return
    from torch.utils.tensorboard import SummaryWriter
    with SummaryWriter(str(out / "tensorboard")) as writer:
        for i, f in enumerate(modes.frequencies):
            writer.add_scalar("modes/frequency_hz", float(f), i)
        for i, fig in figures.items():
            writer.add_figure(f"modes/shape_{i:02d}", fig, 0, close=False)
