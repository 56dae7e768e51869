"""Motions for any command: what a config's ``data`` names, their torsos (a moving
base), their generating fields where the data carries them, and whether each motion's
samples resolve its torques."""
from __future__ import annotations

import warnings
from pathlib import Path

from ..errors import InputError
from ..io import basis as basis_io
from ..motions import motion as motion_mod
from ..motions import spline
from ..motions.torso import BaseMotion, Bases
from ..physics.body import Body
from . import gestures as gestures_mod


def load_motions(data, body: Body, strict: bool = False) -> list:
    """Motions named by ``data``: "gestures" (the built-in library), a folder of .npz
    files (bad files are skipped with a warning naming them, unless ``strict``), one
    .npz file, or a list of them. Raises :class:`~tflearn.motions.motion.MotionFileError` naming
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


def skipped_files(data, body: Body, motions: list) -> list:
    """The bad files that :func:`load_motions` skipped in the folder ``data`` names, each
    {"file", "reason"}: the .npz files there that gave none of ``motions`` (a motion is
    named by its file's stem), with the problem that file's
    :class:`~tflearn.motions.motion.MotionFileError` names; [] when ``data`` names no folder."""
    if data == "gestures" or not isinstance(data, (str, Path)) or not Path(data).is_dir():
        return []
    loaded, skipped = {m.name for m in motions}, []
    for file in sorted(Path(data).glob("*.npz")):
        if file.stem not in loaded:
            try:
                motion_mod.load(file, body)
            except motion_mod.MotionFileError as err:
                skipped.append({"file": str(file), "reason": err.problem})
    return skipped


def named_motions(data, body: Body, names: list, where: str) -> list:
    """The motions ``names`` of ``data`` (:func:`load_motions`), in that order. Raises
    :class:`~tflearn.errors.InputError`, after ``where``, naming those ``data`` lacks."""
    found = {m.name: m for m in load_motions(data, body) if m.name in names}
    missing = [n for n in names if n not in found]
    if missing:
        raise InputError(f"{where}: motion(s) {', '.join(map(repr, missing))} are not in the run's "
                         f"data ({data!r})")
    return [found[n] for n in names]


def torsos(data, motions: list, torso: str = "fixed") -> Bases | None:
    """The motions' moving bases for ``torso: moving`` (None for ``fixed``): each motion's
    torso file ``torso/NAME.npz`` beside the motion files (``tflearn bvh import`` writes
    them there; its times in the clock of the motion's own samples), one per motion of
    :func:`load_motions` ``(data, ...)``, starting at the motion's first sample. Raises
    :class:`~tflearn.motions.motion.MotionFileError` naming a missing torso file or one whose
    times do not cover its motion's, or when ``data`` names no motion files (the
    built-in gestures have no torso)."""
    if torso == "fixed":
        return None
    if data == "gestures":
        raise motion_mod.MotionFileError("gestures", "torso: moving needs motions with torso files (tflearn "
                                                     "bvh import writes them); the gestures have none")
    if isinstance(data, (str, Path)):            # a folder, or one file: one folder for all
        folders = [Path(data) if Path(data).is_dir() else Path(data).parent] * len(motions)
    else:                                        # a list of files, one per motion
        folders = [Path(p).parent for p in data]
    paths = [folder / "torso" / f"{m.name}.npz" for folder, m in zip(folders, motions)]
    for path, m in zip(paths, motions):
        if not path.is_file():
            raise motion_mod.MotionFileError(str(path), f"no torso file for motion {m.name!r} "
                                                        f"(torso: moving)")
    bases = [BaseMotion.load(p) for p in paths]
    for path, m, b in zip(paths, motions, bases):
        lo, hi = b.span
        t0, t1 = float(m.t[0]), float(m.t[-1])
        if t0 < lo - 1e-6 or t1 > hi + 1e-6:
            raise motion_mod.MotionFileError(str(path), f"the torso covers {lo:.3f}–{hi:.3f} s, motion "
                                                        f"{m.name!r} {t0:.3f}–{t1:.3f} s")
    return Bases.of(bases, start=[float(m.t[0]) for m in motions])


def generating_bases(data, body: Body, names: list) -> dict:
    """The generating parameters of the motions ``names`` of ``data``, where the data
    carries them: {name: a LearnedBasis holding that motion alone, its fields and
    weights}. The built-in gestures' own programs
    (:func:`tflearn.data.gestures.generating_bases`), or a file NAME.json (basis format,
    one motion named NAME) beside a motion file NAME.npz — what ``tflearn gestures --out``
    and the benchmarks write. Motions without one are left out ({} for data that carries
    none, such as recorded motion); a NAME.json that is not such a file for this body
    is warned about, naming it, and left out."""
    if data == "gestures":
        return {n: lb for lb in gestures_mod.generating_bases(body=body) for n in lb.names if n in names}
    if isinstance(data, (str, Path)):
        p = Path(data)
        files = {n: p / f"{n}.json" for n in names} if p.is_dir() else {p.stem: p.with_suffix(".json")}
    else:
        files = {Path(f).stem: Path(f).with_suffix(".json") for f in data}
    out = {}
    for name, file in files.items():
        if name not in names or not file.is_file():
            continue
        try:
            lb = basis_io.load(file)
        except basis_io.BasisFileError as err:
            warnings.warn(f"{err}; not read as motion {name!r}'s generating fields", stacklevel=2)
            continue
        if lb.names != [name] or lb.body.nv != body.nv:
            warnings.warn(f"{file}: not read as motion {name!r}'s generating fields: it holds motion(s) "
                          f"{', '.join(lb.names)} over {lb.body.nv} coordinates", stacklevel=2)
            continue
        out[name] = lb
    return out


def check_resolution(body: Body, motions: list) -> list:
    """Each motion's :func:`tflearn.motions.spline.torque_resolution`; warns, naming the motion,
    for those above :data:`tflearn.motions.spline.RESOLVED` (too fast for their sampling)."""
    eps = [spline.torque_resolution(body, m) for m in motions]
    for m, e in zip(motions, eps):
        if e > spline.RESOLVED:
            warnings.warn(f"motion {m.name!r}: its samples do not resolve it at {m.rate:.0f} Hz "
                          f"(spline torques an estimated {100 * e:.1f}% off, above "
                          f"{100 * spline.RESOLVED:.0f}%); it may not be reproduced. "
                          f"Sample it faster or smooth it.", stacklevel=2)
    return eps
