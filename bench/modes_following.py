"""How a PD controller with the analysis stiffness follows a mode-driven set point
(docs/modes.md, "Dynamic: following"): the arm of configs/modes/arm.yaml, mode 0 alone
at α = 0.02 rad, drive frequency f̃ and damping c varied.

    PYTHONPATH=. python bench/modes_following.py          (a few minutes on one core)

Per case: the RMS and largest joint error |θ_set ⊖ θ| over the last two drive periods,
and the ratio of the body's to the set point's amplitude at f̃ in the mode's coordinate
(least squares over the whole run, with a free oscillation at f₀ fitted beside it: the
start-up transient) against the single-mode prediction |H| = ω² / |ω² − ω̃² + i γ ω̃|, with γ = c uᵀu the
mode's damping (the PD's damping c·I projected on the M-orthonormal shape u). The
damping is kept small: c·I on the hand's twist (inertia 2·10⁻⁴ kg·m²) makes the ODE
stiff for dopri5 (c = 2 needs more than 10⁵ evaluations for 15 s).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from tflearn import config
from tflearn.modes import command as modal
from tflearn.modes import motion as mm
from tflearn.modes.config import ModesConfig
from tflearn.physics.configspace import difference
from tflearn.simulation.simulate import SimOptions

ROOT = Path(__file__).resolve().parents[1]


def drive_amplitude(t: np.ndarray, c: np.ndarray, fd: float, f0: float) -> float:
    """Amplitude of the f̃ component of c(t), least-squares fitted together with a free
    oscillation at f₀ (the start-up transient, which decays slowly at small damping)."""
    cols = [np.ones_like(t)]
    for f in (fd, f0):                 # fd first: coef[1], coef[2]
        cols += [np.sin(2 * np.pi * f * t), np.cos(2 * np.pi * f * t)]
    coef = np.linalg.lstsq(np.stack(cols, 1), c, rcond=None)[0]
    return float(np.hypot(coef[1], coef[2]))


def case(modes, ratio: float, c: float, alpha: float = 0.02, periods: float = 6.0):
    f0 = float(modes.frequencies[0])
    fd = ratio * f0
    drives = [mm.ModeDrive(0, amplitude=alpha, frequency=fd)]
    t = torch.linspace(0.0, periods / fd, int(periods * 40) + 1, dtype=torch.float64)
    fol = mm.follow(modes, drives, t, damping=c, options=SimOptions(max_evals=None))
    tail = (t >= (periods - 2) / fd).numpy()
    target = mm.set_point(modes, drives, t)
    err = difference(modes.body, fol.trajectory.q, target).norm(dim=-1).numpy()[tail]
    u = modes.shapes[:, 0]
    w, wd, g = 2 * np.pi * f0, 2 * np.pi * fd, c * float(u @ u)
    predicted = w * w / abs(w * w - wd * wd + 1j * g * wd)
    if ratio == 1.0:
        amp = float("nan")             # at resonance the response has not settled
    else:
        tn = t.numpy()
        amp = (drive_amplitude(tn, mm.modal_coordinate(modes, fol.trajectory.q, 0), fd, f0)
               / drive_amplitude(tn, mm.modal_coordinate(modes, target, 0), fd, f0))
    return fd, c, float(np.sqrt(np.mean(err ** 2))), float(err.max()), amp, predicted


def main() -> None:
    torch.set_num_threads(1)
    cfg = config.load(ROOT / "configs" / "modes" / "arm.yaml", schema=ModesConfig)
    modes = modal.analyse_config(cfg)
    print("| f̃ / f₀ | f̃ (Hz) | c (N·m·s/rad) | rms error (rad) | max error (rad) | "
          "amplitude ratio | predicted |")
    print("|---:|---:|---:|---:|---:|---:|---:|")
    for ratio, c in ((0.5, 0.05), (0.5, 0.2), (2.0, 0.05), (2.0, 0.2), (1.0, 0.2)):
        fd, c, rms, mx, amp, pred = case(modes, ratio, c)
        shown = "—" if np.isnan(amp) else f"{amp:.3f}"
        print(f"| {ratio} | {fd:.4f} | {c} | {rms:.4f} | {mx:.4f} | {shown} | {pred:.3f} |",
              flush=True)


if __name__ == "__main__":
    main()
