"""The measured tables of docs/modes.md: frequencies of the configs/modes bodies, the free
vibration check, and the modes each gesture field excites.

    PYTHONPATH=. python bench/modes_tables.py            (about 15 s on one core)

Prints markdown. The PD-following figures of the arm come from ``tflearn modes
configs/modes/arm.yaml`` (its last printed line), not from here.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from tflearn import config
from tflearn.data import gestures
from tflearn.modes import analysis as md
from tflearn.modes import command as modal
from tflearn.modes import motion as mm
from tflearn.modes.config import ModesConfig
from tflearn.physics import body as tb
from tflearn.simulation.simulate import SimOptions

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ("arm", "linear_creature", "loop_creature", "human")   # human: needs the mocap data


def frequency_table(rows: int = 12) -> str:
    res = {name: modal.analyse_config(config.load(ROOT / "configs" / "modes" / f"{name}.yaml",
                                                  schema=ModesConfig)) for name in CONFIGS}
    lines = ["| mode | " + " | ".join(f"{n} (Hz)" for n in CONFIGS) + " |",
             "|---:|" + "---:|" * len(CONFIGS)]
    for i in range(rows):
        cells = []
        for n in CONFIGS:
            m = res[n]
            if i >= m.frequencies.size:
                cells.append("")
            else:
                cells.append("rigid" if m.rigid[i] else f"{m.frequencies[i]:.4f}")
        lines.append(f"| {i} | " + " | ".join(cells) + " |")
    lines.append("| DOF | " + " | ".join(str(res[n].frequencies.size) for n in CONFIGS) + " |")
    return "\n".join(lines)


def free_vibration() -> str:
    """The arm at the test's pose released along each mode (10⁻⁴), both charts."""
    body = tb.arm()
    pose = np.array([0.3, -0.2, 0.5, -1.0, 0.2, 0.1, -0.3])
    lines = ["| chart | mode | computed (Hz) | measured (Hz) | relative error |",
             "|---|---:|---:|---:|---:|"]
    for chart in md.CHARTS:
        res = md.analyse(body, pose, md.stiffness_matrix(body, 20.0),
                         options=md.ModalOptions(chart=chart))
        for i in (0, 3, 6):
            f = res.frequencies[i]
            q = mm.retract(res, torch.as_tensor(1e-4 * res.joint_shapes[:, i]))
            t = torch.linspace(0.0, 3.3 / f, 200, dtype=torch.float64)
            fol = mm.follow(res, [], t, q_start=q, options=SimOptions(rtol=1e-7, atol=1e-11))
            fm = mm.measured_frequency(t.numpy(), mm.modal_coordinate(res, fol.trajectory.q, i))
            lines.append(f"| {chart} | {i} | {f:.6f} | {fm:.6f} | {fm / f - 1:.1e} |")
    return "\n".join(lines)


def dominant_joint(body, u: np.ndarray) -> str:
    """The joint (shoulder, elbow, wrist for the arm) with the largest share of shape u."""
    from tflearn.plots.figures import JOINT_NAMES
    names = [JOINT_NAMES.get(n, n) for n in md.joint_names(body)]
    sizes = [np.linalg.norm(u[body.slice(i)]) for i, link in enumerate(body.links) if link.dof]
    return names[int(np.argmax(sizes))]


def gesture_fields() -> str:
    body = tb.arm()
    lines = ["| gesture | field | k | lowest frequencies about η (Hz) | modes excited from rest "
             "(share of spring energy, joint moving most) |", "|---|---:|---:|---|---|"]
    for name, g in gestures.GESTURES.items():
        ms = md.field_modes(body, g.eta, [k * np.eye(7) for k in g.k])
        for i, m in enumerate(ms):
            e = md.excitation(m, np.zeros(7))
            top = [k for k in np.argsort(-e)[:3] if e[k] >= 0.05]
            desc = ", ".join(f"{k} ({100 * e[k]:.0f}%, {dominant_joint(body, m.shapes[:, k])})"
                             for k in top)
            freqs = " ".join(f"{f:.2f}" for f in m.frequencies[:4])
            lines.append(f"| {name} | {i} | {g.k[i]} | {freqs} | {desc} |")
    return "\n".join(lines)


if __name__ == "__main__":
    torch.set_num_threads(1)
    print("## Frequencies\n\n" + frequency_table())
    print("\n## Free vibration of the arm\n\n" + free_vibration())
    print("\n## Gesture fields\n\n" + gesture_fields())
