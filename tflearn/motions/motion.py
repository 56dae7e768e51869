"""Sampled limb motions: a container, ``.npz`` files and recordings of joint angles.

A :class:`Motion` holds T samples of a body's coordinates ν (T×nv, the layout of
:mod:`tflearn.physics.body`: rotation vectors for ball joints, angles for hinges) at strictly
increasing times t (T), and optionally the velocities (T×nv, body convention: a ball
joint's is the child's angular velocity relative to its parent in the child frame, a
hinge's is θ̇). Everything is float64 torch.

Files are ``.npz`` archives holding float arrays ``t`` (T), ``q`` (T×nv) and optionally
``qd`` (T×nv); the motion is named after the file stem. Bad files raise
:class:`MotionFileError` naming the file and the problem (:func:`load_dir` skips them
with a :class:`MotionFileWarning` unless ``strict``). Files are read without pickle
support (``allow_pickle=False``) and written atomically.

Recordings of joint angles (motion capture, animation tools) come in through
:func:`from_euler` (arrays: per ball joint three Euler angles in a stated scipy order,
per hinge one angle) or :func:`read_csv` (a CSV with a header row, :func:`columns`);
ball joints become principal rotation vectors and velocities are left to the spline
(:mod:`tflearn.motions.spline`, which also gives a motion's inverse-dynamics torques).
"""
from __future__ import annotations

import math
import warnings
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from ..errors import InputError
from ..io.files import replacing
from ..physics.body import Body, arm
from ..physics.configspace import wrap_rotvec

__all__ = ["DTYPE", "ARRAYS", "MIN_SAMPLES", "JOINT_COLUMNS", "MotionError", "MotionFileError",
           "MotionFileWarning", "Motion", "load", "save", "load_dir", "columns", "euler_to_rotvec",
           "from_euler", "read_csv"]

DTYPE = torch.float64
ARRAYS = ("t", "q", "qd")
MIN_SAMPLES = 4


# ----------------------------------------------------------------------------------------
# Motions and their validation
# ----------------------------------------------------------------------------------------

class MotionError(InputError):
    """An invalid motion. ``problem`` is the message without the motion's name."""

    def __init__(self, where: str, problem: str):
        super().__init__(f"{where}: {problem}")
        self.where, self.problem = where, problem


class MotionFileError(MotionError):
    """A motion file (or directory of files) that cannot be loaded; names the file(s)."""


class MotionFileWarning(UserWarning):
    """A bad motion file skipped by :func:`load_dir`; the message names the file."""


class _Problem(Exception):
    """Internal: one validation problem, to be wrapped with the motion's or file's name."""


def _as_array(name: str, x) -> np.ndarray:
    """x as a float64 numpy array (raises _Problem for a non-numeric array)."""
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    arr = np.asarray(x)
    if arr.dtype.kind not in "iuf":
        raise _Problem(f"array {name!r} is not a real numeric array (dtype {arr.dtype})")
    return arr.astype(np.float64)


def _check_finite(name: str, arr: np.ndarray) -> None:
    bad = ~np.isfinite(arr)
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        idx = idx[0] if len(idx) == 1 else idx
        raise _Problem(f"array {name!r} contains NaN or Inf (first at index {idx})")


def _validate(t, q, qd, body: Body):
    """Check and convert (t, q, qd) to float64 numpy; raises _Problem with the first issue."""
    t = _as_array("t", t)
    if t.ndim != 1:
        raise _Problem(f"array 't' has shape {t.shape}, expected a 1-D array of T times")
    T = t.shape[0]
    if T < MIN_SAMPLES:
        raise _Problem(f"has {T} samples, at least {MIN_SAMPLES} are needed")
    _check_finite("t", t)
    dt = np.diff(t)
    if (dt <= 0).any():
        i = int(np.argmax(dt <= 0)) + 1
        raise _Problem(f"times 't' are not strictly increasing "
                       f"(t[{i}] = {float(t[i])!r} <= t[{i - 1}] = {float(t[i - 1])!r})")
    expected = (T, body.nv)
    q = _as_array("q", q)
    if q.shape != expected:
        raise _Problem(f"array 'q' has shape {q.shape}, expected {expected} "
                       f"for the {body.name} body")
    _check_finite("q", q)
    if qd is not None:
        qd = _as_array("qd", qd)
        if qd.shape != expected:
            raise _Problem(f"array 'qd' has shape {qd.shape}, expected {expected} "
                           f"(the shape of 'q')")
        _check_finite("qd", qd)
    return t, q, qd


@dataclass(eq=False)
class Motion:
    """A sampled motion of a body.

    Attributes:
        name: motion name (a file's stem).
        t: sample times (T), strictly increasing, T ≥ 4.
        q: coordinates ν (T×nv); for the arm [shoulder rotation vector (3), elbow angle
            (1), wrist rotation vector (3)].
        qd: optional velocities (T×nv), body convention (see :mod:`tflearn.physics.body`).
        body: the body the coordinates belong to (default: :func:`tflearn.physics.body.arm`).
    Arrays are converted to float64 torch tensors and validated on construction
    (:class:`MotionError` names the motion and the problem).
    """

    name: str
    t: torch.Tensor
    q: torch.Tensor
    qd: Optional[torch.Tensor] = None
    body: Optional[Body] = None

    def __post_init__(self):
        self.name = str(self.name)
        if self.body is None:
            self.body = arm()
        try:
            t, q, qd = _validate(self.t, self.q, self.qd, self.body)
        except _Problem as err:
            raise MotionError(f"motion {self.name!r}", str(err)) from None
        self.t = torch.from_numpy(t)
        self.q = torch.from_numpy(q)
        self.qd = None if qd is None else torch.from_numpy(qd)

    @property
    def T(self) -> int:
        """Number of samples."""
        return self.t.shape[0]

    @property
    def nv(self) -> int:
        return self.q.shape[1]

    @property
    def duration(self) -> float:
        """t[-1] − t[0], seconds."""
        return float(self.t[-1] - self.t[0])

    @property
    def rate(self) -> float:
        """Samples per second, (T − 1) / (t[-1] − t[0]) (exact for uniform sampling)."""
        return (self.T - 1) / self.duration


# ----------------------------------------------------------------------------------------
# Files
# ----------------------------------------------------------------------------------------

def _unreadable(err: Exception) -> str:
    if "pickle" in str(err):
        return "holds pickled (object) arrays, which are never loaded (allow_pickle=False)"
    return f"not a readable .npz file ({type(err).__name__}: {err})"


def _read_npz(path: Path) -> dict:
    """The arrays of an .npz file (raises _Problem when unreadable or malformed)."""
    if not path.is_file():
        raise _Problem("no such file" if not path.exists() else "not a regular file")
    if not zipfile.is_zipfile(path):
        raise _Problem("not an .npz archive (not a zip file)")
    try:
        data = np.load(path, allow_pickle=False)
        with data:
            arrays = {k: data[k] for k in data.files}
    except Exception as err:
        raise _Problem(_unreadable(err)) from None
    missing = [k for k in ("t", "q") if k not in arrays]
    if missing:
        raise _Problem(f"missing array {' and '.join(map(repr, missing))} "
                       f"(found {sorted(arrays)})")
    extra = sorted(set(arrays) - set(ARRAYS))
    if extra:
        raise _Problem(f"unexpected array(s) {', '.join(map(repr, extra))} "
                       f"(expected 't', 'q' and optionally 'qd')")
    return arrays


def load(path, body: Optional[Body] = None) -> Motion:
    """Read a motion from an ``.npz`` file with arrays t (T), q (T×nv), optional qd (T×nv).

    ``body`` (default: the arm) fixes nv. Raises :class:`MotionFileError` naming the file
    and the problem (unreadable file, missing array, wrong shape, NaN/Inf, non-increasing
    t, fewer than 4 samples).
    """
    path = Path(path)
    body = arm() if body is None else body
    try:
        arrays = _read_npz(path)
        t, q, qd = _validate(arrays["t"], arrays["q"], arrays.get("qd"), body)
    except _Problem as err:
        raise MotionFileError(str(path), str(err)) from None
    return Motion(path.stem, t, q, qd, body)


def save(motion: Motion, path) -> None:
    """Write a motion to ``path`` (.npz, exactly that name) as float64 t, q and qd if any.

    Atomic: the archive is written to a temporary file in the same folder, then renamed
    over ``path`` (``os.replace``), so readers see the old file or the whole new one.
    """
    path = Path(path)
    arrays = {"t": motion.t.numpy(), "q": motion.q.numpy()}
    if motion.qd is not None:
        arrays["qd"] = motion.qd.numpy()
    with replacing(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, **arrays)


def load_dir(path, body: Optional[Body] = None, strict: bool = False) -> list[Motion]:
    """All ``*.npz`` motions in a directory, sorted by name.

    Non-strict (default): every readable file is loaded and each bad one is skipped with
    one :class:`MotionFileWarning` "<file>: <problem>; skipped". Strict: the first bad
    file (in name order) raises its :class:`MotionFileError`. Either way a path that is
    not a directory, or one with no readable motion file (none at all, or all bad:
    the problems are listed), raises :class:`MotionFileError` naming the directory.
    """
    path = Path(path)
    if not path.is_dir():
        raise MotionFileError(str(path), "not a directory")
    motions, errors = [], []
    for file in sorted(path.glob("*.npz")):
        try:
            motions.append(load(file, body))
        except MotionFileError as err:
            if strict:
                raise
            errors.append(err)
    if not motions:
        found = "; ".join(map(str, errors)) if errors else "no .npz files"
        raise MotionFileError(str(path), f"no readable motion files ({found})")
    for err in errors:
        warnings.warn(f"{err}; skipped", MotionFileWarning, stacklevel=2)
    return sorted(motions, key=lambda m: m.name)


# ----------------------------------------------------------------------------------------
# Recordings: Euler angles and CSV files
# ----------------------------------------------------------------------------------------

#: CSV column stems of the arm's joints (by link name); other bodies use their link names.
JOINT_COLUMNS = {"upper_arm": "shoulder", "forearm": "elbow", "hand": "wrist"}


def _joint_names(body: Body) -> list:
    """(link, column stem) of each moving joint."""
    return [(link, JOINT_COLUMNS.get(link.name, link.name) if body.name == "arm" else link.name)
            for link in body.links if link.joint in ("ball", "hinge")]


def columns(body: Optional[Body] = None, order: Optional[str] = None) -> list[str]:
    """The CSV columns of a body's recording: ``t``, then per joint in link order
    ``NAME_x, NAME_y, NAME_z`` (a ball joint: its angles about x, y and z) or ``NAME`` (a
    hinge), where NAME is the joint's name (the arm: ``shoulder``, ``elbow``, ``wrist``;
    another body: its link's name). For the arm: t, shoulder_x, shoulder_y, shoulder_z,
    elbow, wrist_x, wrist_y, wrist_z. With an Euler ``order`` a ball joint's three columns
    come in that sequence (``"ZYX"``: NAME_z, NAME_y, NAME_x), the layout of
    :func:`from_euler`'s angles."""
    body = arm() if body is None else body
    axes = "xyz" if order is None else _check_order(order, tait_bryan=True).lower()
    out = ["t"]
    for link, name in _joint_names(body):
        out += [f"{name}_{ax}" for ax in axes] if link.joint == "ball" else [name]
    return out


def _check_order(order: str, tait_bryan: bool = False) -> str:
    """``order`` if it is an Euler sequence scipy accepts (``tait_bryan``: three different
    axes, as a CSV's NAME_x, NAME_y, NAME_z columns need); else ValueError."""
    ok = (isinstance(order, str) and len(order) == 3 and
          (set(order) <= set("XYZ") or set(order) <= set("xyz")) and
          order[0] != order[1] and order[1] != order[2])
    if not ok or (tait_bryan and len(set(order)) != 3):
        what = "three different axes" if tait_bryan else "three axes, none twice in a row,"
        raise ValueError(f"Euler order must be {what} from 'XYZ' (intrinsic) or 'xyz' "
                         f"(extrinsic); got {order!r}")
    return order


def euler_to_rotvec(angles, order: str = "XYZ", degrees: bool = True) -> np.ndarray:
    """Principal rotation vectors (...×3, ‖v‖ ≤ π) of Euler angles (...×3), the k-th angle
    about axis ``order[k]``: upper case intrinsic (about the turning frame's axes,
    R = R_1 R_2 R_3), lower case extrinsic (about the fixed axes, R = R_3 R_2 R_1),
    as :meth:`scipy.spatial.transform.Rotation.from_euler`."""
    from scipy.spatial.transform import Rotation
    angles = np.asarray(angles, dtype=np.float64)
    shape = angles.shape
    rv = Rotation.from_euler(_check_order(order), angles.reshape(-1, 3), degrees=degrees).as_rotvec()
    return wrap_rotvec(torch.from_numpy(rv)).numpy().reshape(shape)


def from_euler(name: str, t, angles, order: str = "XYZ", degrees: bool = True,
               body: Optional[Body] = None) -> Motion:
    """A motion from recorded joint angles.

    Args:
        name: the motion's name.
        t: sample times (T), seconds, strictly increasing.
        angles: T×n, per joint in link order: a ball joint's three Euler angles, the k-th
            about axis ``order[k]``; a hinge's angle (the arm: shoulder 3, elbow 1, wrist 3).
        order: the Euler sequence, as scipy's
            :meth:`~scipy.spatial.transform.Rotation.from_euler`: ``"XYZ"`` (upper case)
            is intrinsic — about x, then the new y, then the newer z, R = Rx·Ry·Rz;
            ``"xyz"`` (lower case) is extrinsic — about the fixed x, y, then z,
            R = Rz·Ry·Rx. No axis twice in a row (proper Euler orders such as ``"ZXZ"``
            are accepted too).
        degrees: angles in degrees (default) or radians.
        body: the body (default: the arm).

    Each ball joint's rotation (relative to its zero orientation R₀, the child frame in
    the parent frame) becomes its principal rotation vector (‖v‖ ≤ π: angles past 180°
    wrap); a hinge's angle is converted to radians and kept as it is. Velocities are left
    to the spline (``qd`` is None). Raises :class:`MotionError` (bad times or shapes) and
    ValueError (a bad order).
    """
    body = arm() if body is None else body
    _check_order(order)
    a = _as_array_or_raise(name, "angles", angles)
    n = sum(3 if link.joint == "ball" else link.dof for link in body.links)
    if a.ndim != 2 or a.shape[1] != n:
        raise MotionError(f"motion {name!r}", f"angles have shape {a.shape}, expected "
                          f"(T, {n}) for the {body.name} body")
    q = np.empty_like(a)
    for i, link in enumerate(body.links):
        sl = body.slice(i)
        if link.joint == "ball":
            q[:, sl] = euler_to_rotvec(a[:, sl], order, degrees)
        elif link.joint == "hinge":
            q[:, sl] = np.deg2rad(a[:, sl]) if degrees else a[:, sl]
    return Motion(name, t, q, None, body)


def _as_array_or_raise(name: str, what: str, x) -> np.ndarray:
    try:
        arr = _as_array(what, x)
        _check_finite(what, arr)
    except _Problem as err:
        raise MotionError(f"motion {name!r}", str(err)) from None
    return arr


def _csv_rows(path: Path):
    """(line number, fields) of a CSV file's non-blank, non-comment (#) lines."""
    import csv
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise _Problem("no such file") from None
    except IsADirectoryError:
        raise _Problem("not a regular file") from None
    except OSError as err:
        raise _Problem(f"cannot read ({err.strerror})") from None
    except UnicodeDecodeError as err:
        raise _Problem(f"not a text file (not UTF-8 at byte {err.start})") from None
    for lineno, line in enumerate(text.splitlines(), 1):
        if line.strip() and not line.lstrip().startswith("#"):
            yield lineno, [x.strip() for x in next(csv.reader([line]))]


def _is_number(text: str) -> bool:
    try:
        float(text)
        return True
    except ValueError:
        return False


def read_csv(path, order: str = "XYZ", degrees: bool = True, body: Optional[Body] = None) -> Motion:
    """A motion from a CSV recording of joint angles (see :func:`columns`, :func:`from_euler`).

    The file: a header row naming the columns — for the arm ``t, shoulder_x, shoulder_y,
    shoulder_z, elbow, wrist_x, wrist_y, wrist_z``, in any order (case and spaces
    ignored) — then one row per sample: t in seconds, each ball joint's Euler angles
    (``NAME_x`` the angle about x, applied in the sequence ``order``, upper case
    intrinsic, lower case extrinsic, as scipy), each hinge's angle, in degrees (or
    radians: ``degrees=False``). Blank lines and lines starting with ``#`` are skipped.
    The motion is named after the file stem.

    Raises :class:`MotionFileError` naming the file, the line (and column) and the
    problem: no header row, missing or unknown columns, a row with the wrong number of
    values, a value that is not a finite number, times not strictly increasing, fewer
    than 4 samples.
    """
    path = Path(path)
    body = arm() if body is None else body
    names = columns(body, order)        # in the sequence from_euler takes
    try:
        rows = _csv_rows(path)
        first = next(rows, None)
        if first is None:
            raise _Problem(f"empty: expected a header row ({', '.join(columns(body))}) and samples")
        lineno, header = first
        if all(_is_number(x) for x in header if x):
            raise _Problem(f"line {lineno}: missing header row (the first row must name the "
                           f"columns: {', '.join(columns(body))}; found numbers)")
        key = [h.lower().replace(" ", "") for h in header]
        missing = [n for n in names if n not in key]
        unknown = [h for h, k in zip(header, key) if k not in names]
        dup = sorted({h for h in key if key.count(h) > 1})
        if missing or unknown or dup:
            bits = ([f"missing column(s) {', '.join(map(repr, missing))}"] if missing else []) + \
                   ([f"unknown column(s) {', '.join(map(repr, unknown))}"] if unknown else []) + \
                   ([f"repeated column(s) {', '.join(map(repr, dup))}"] if dup else [])
            raise _Problem(f"line {lineno}: header: {'; '.join(bits)} "
                           f"(expected {', '.join(columns(body))})")
        perm = [key.index(n) for n in names]
        data, lines = [], []
        for lineno, fields in rows:
            if len(fields) != len(header):
                raise _Problem(f"line {lineno}: {len(fields)} values, expected {len(header)} "
                               f"({', '.join(header)})")
            row = []
            for c, text in enumerate(fields):
                try:
                    x = float(text)
                except ValueError:
                    x = None
                if x is None or not math.isfinite(x):
                    what = "is not a number" if x is None else "is not finite"
                    raise _Problem(f"line {lineno}, column {c + 1} ({header[c]!r}): "
                                   f"{text!r} {what}")
                row.append(x)
            data.append([row[i] for i in perm])
            lines.append(lineno)
        if not data:
            raise _Problem("no samples after the header row")
        arr = np.array(data, dtype=np.float64)
        t = arr[:, 0]
        bad = np.flatnonzero(np.diff(t) <= 0)
        if bad.size:
            i = int(bad[0]) + 1
            raise _Problem(f"line {lines[i]}: times 't' are not strictly increasing "
                           f"(t = {t[i]!r} after t = {t[i - 1]!r} on line {lines[i - 1]})")
        try:
            motion = from_euler(path.stem, t, arr[:, 1:], order, degrees, body)
        except MotionError as err:
            raise _Problem(err.problem) from None
    except _Problem as err:
        raise MotionFileError(str(path), str(err)) from None
    return motion
