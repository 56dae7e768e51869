"""Motions for any command: what a config's ``data`` names, and whether each motion's
samples resolve its torques."""
from __future__ import annotations

import warnings
from pathlib import Path

from . import gestures as gestures_mod
from . import motion as motion_mod
from .body import Body


def load_motions(data, body: Body, strict: bool = False) -> list:
    """Motions named by ``data``: "gestures" (the built-in library), a folder of .npz
    files (bad files are skipped with a warning naming them, unless ``strict``), one
    .npz file, or a list of them. Raises :class:`~tflearn.motion.MotionFileError` naming
    the file and the problem, and when nothing is left to load."""
    if data == "gestures":
        return [m for m, _ in gestures_mod.generate(body)]
    if isinstance(data, (str, Path)):
        p = Path(data)
        if p.is_dir():
            return motion_mod.load_dir(p, body, strict=strict)
        return [motion_mod.load(p, body)]
    if not data:
        raise motion_mod.MotionFileError("data", "an empty list of motion files")
    return [motion_mod.load(p, body) for p in data]


def check_resolution(body: Body, motions: list) -> list:
    """Each motion's :func:`tflearn.motion.torque_resolution`; warns, naming the motion,
    for those above :data:`tflearn.motion.RESOLVED` (too fast for their sampling)."""
    eps = [motion_mod.torque_resolution(body, m) for m in motions]
    for m, e in zip(motions, eps):
        if e > motion_mod.RESOLVED:
            warnings.warn(f"motion {m.name!r}: its samples do not resolve it at {m.rate:.0f} Hz "
                          f"(spline torques an estimated {100 * e:.1f}% off, above "
                          f"{100 * motion_mod.RESOLVED:.0f}%); it may not be reproduced. "
                          f"Sample it faster or smooth it.", stacklevel=2)
    return eps
