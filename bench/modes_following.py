"""How a PD controller with the analysis stiffness follows a mode-driven set point
(docs/modes.md, "Dynamic: following"): the arm of configs/modes/arm.yaml, mode 0 alone
at α = 0.05 rad, drive frequency f̃ and damping c varied.

    PYTHONPATH=. python bench/modes_following.py          (a few minutes on one core)

Per case: the RMS and largest joint error |θ_set ⊖ θ| over the last two drive periods,
and the ratio of the body's to the set point's amplitude in the mode's coordinate
against the single-mode prediction |H| = ω² / |ω² − ω̃² + i γ ω̃|, with γ = c uᵀu the
mode's damping (the PD's damping c·I projected on the M-orthonormal shape u).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from tflearn import config, modal
from tflearn import modal_motion as mm
from tflearn.configspace import difference
from tflearn.modal_config import ModesConfig

ROOT = Path(__file__).resolve().parents[1]


def case(modes, ratio: float, c: float, alpha: float = 0.05, periods: float = 6.0):
    f0 = float(modes.frequencies[0])
    fd = ratio * f0
    drives = [mm.ModeDrive(0, amplitude=alpha, frequency=fd)]
    t = torch.linspace(0.0, periods / fd, int(periods * 40) + 1, dtype=torch.float64)
    fol = mm.follow(modes, drives, t, damping=c)
    tail = t >= (periods - 2) / fd
    target = mm.set_point(modes, drives, t)
    err = difference(modes.body, fol.trajectory.q, target).norm(dim=-1)[tail]
    body_amp = np.abs(mm.modal_coordinate(modes, fol.trajectory.q, 0)[tail.numpy()]).max()
    set_amp = np.abs(mm.modal_coordinate(modes, target, 0)[tail.numpy()]).max()
    u = modes.shapes[:, 0]
    w, wd, g = 2 * np.pi * f0, 2 * np.pi * fd, c * float(u @ u)
    predicted = w * w / abs(w * w - wd * wd + 1j * g * wd)
    return (fd, c, float(err.pow(2).mean().sqrt()), float(err.max()), body_amp / set_amp,
            predicted)


def main() -> None:
    torch.set_num_threads(1)
    cfg = config.load(ROOT / "configs" / "modes" / "arm.yaml", schema=ModesConfig)
    modes = modal.analyse_config(cfg)
    print("| f̃ / f₀ | f̃ (Hz) | c (N·m·s/rad) | rms error (rad) | max error (rad) | "
          "amplitude ratio | predicted |")
    print("|---:|---:|---:|---:|---:|---:|---:|")
    for ratio in (0.5, 1.0, 2.0):
        for c in (0.5, 2.0):
            fd, c, rms, mx, amp, pred = case(modes, ratio, c)
            print(f"| {ratio} | {fd:.4f} | {c} | {rms:.4f} | {mx:.4f} | {amp:.3f} | {pred:.3f} |")


if __name__ == "__main__":
    main()
