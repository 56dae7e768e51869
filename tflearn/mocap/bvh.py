"""BVH motion-capture files: a reader and a writer for skeletons and their frames.

A BVH file has a HIERARCHY (a tree of joints; each has an ``OFFSET`` from its parent in
the parent's frame, a ``CHANNELS`` list, children and optionally an ``End Site``) and a
MOTION section (``Frames: F``, ``Frame Time: dt`` and F lines of numbers, one per
channel in hierarchy order). Per joint and frame the channels give a local translation
and a local rotation:

    p_j = OFFSET_j, with each ``Xposition``/``Yposition``/``Zposition`` channel replacing
          its component (the root's and, in the Bandai files, every joint's),
    R_j = R_a1(θ1) R_a2(θ2) R_a3(θ3)   for rotation channels a1 a2 a3 in the listed
          order (intrinsic Euler angles in degrees; CMU lists Z Y X, Bandai Z X Y),

and forward kinematics is W_j = W_p R_j, x_j = x_p + W_p p_j (root: W = R, x = p).
Lengths are converted to metres on reading (``scale`` metres per file unit; ``scale=None``
reads it from the skeleton, :func:`file_unit`: :data:`CMU_UNIT` for CMU's joint names,
else the first of :data:`UNITS` — centimetres, the Bandai files' and most BVH's, then
metres, millimetres, inches and CMU's unit — that makes an arm, upper arm plus forearm,
:data:`ARM_RANGE` long; centimetres where no arm is found by its joints' names).

Why not a BVH package: bvhio 1.5.4 (which reads the good files exactly) loops forever
on a file truncated at a line end, raises a bare IndexError on a short frame line,
ignores surplus values and holds angles in float32; a clear error naming the file,
line and problem needs the whole grammar checked anyway. The reader below checks it
and leaves the rotation maths to scipy; a test compares it with bvhio (4e-7 on all 14
shared clips, docs/mocap.md).
Bad files raise :class:`BVHError` (an :class:`~tflearn.errors.InputError`) naming the
file, the line or joint, and the problem.
"""
from __future__ import annotations

import math
import re
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import InputError
from ..io.files import replacing
from . import names

CMU_UNIT = 0.0254 / 0.45     # metres per CMU BVH unit (the ASF length unit, 1/0.45 inch)
CM = 0.01
POSITION = {"Xposition": 0, "Yposition": 1, "Zposition": 2}
ROTATION = {"Xrotation": "X", "Yrotation": "Y", "Zrotation": "Z"}
CMU_NAMES = {"LowerBack", "Spine1", "RightForeArm", "LeftForeArm"}
#: Length units (metres per file unit) tried in turn for a skeleton not named like CMU's.
UNITS = {"cm": CM, "m": 1.0, "mm": 0.001, "inch": 0.0254, "CMU's": CMU_UNIT}
#: How long (m) a human arm is, shoulder to wrist: the length that picks a file's unit.
ARM_RANGE = (0.3, 1.0)


class BVHError(InputError):
    """A BVH file that cannot be read or mapped; the message names the file and where."""

    def __init__(self, path, problem: str):
        super().__init__(f"{path}: {problem}")
        self.path, self.problem = str(path), problem


@dataclass(frozen=True, eq=False)
class Skeleton:
    """A BVH hierarchy and its frames, lengths in metres, angles as rotation matrices.

    Attributes:
        name: the file's stem.
        joints: joint names (J), parents before children (file order).
        parents: parent index of each joint, -1 for the root (J).
        offsets: OFFSET of each joint in its parent's frame, metres (J×3).
        channels: the channel names of each joint (J tuples).
        end_sites: joint index → End Site offset in that joint's frame, metres (3,).
        frame_time: seconds per frame (the header's Frame Time).
        values: the raw channel numbers, file units and degrees (F×C).
        scale: metres per file unit used for the lengths.
        rotations: local rotations R_j (F×J×3×3).
        positions: local translations p_j, metres (F×J×3).
        source: the file it was read from (named by errors about it).
    """

    name: str
    joints: tuple
    parents: tuple
    offsets: np.ndarray
    channels: tuple
    end_sites: dict
    frame_time: float
    values: np.ndarray
    scale: float
    rotations: np.ndarray
    positions: np.ndarray
    source: str = ""

    @property
    def frames(self) -> int:
        return self.values.shape[0]

    def index(self, joint: str) -> int:
        """Index of a joint by name (KeyError if absent)."""
        return self.joints.index(joint)

    def world(self):
        """Forward kinematics: world rotations (F×J×3×3) and positions (F×J×3, metres)."""
        F, J = self.rotations.shape[:2]
        W = np.empty((F, J, 3, 3))
        x = np.empty((F, J, 3))
        for j, p in enumerate(self.parents):
            if p < 0:
                W[:, j], x[:, j] = self.rotations[:, j], self.positions[:, j]
            else:
                W[:, j] = W[:, p] @ self.rotations[:, j]
                x[:, j] = x[:, p] + np.einsum("fab,fb->fa", W[:, p], self.positions[:, j])
        return W, x


# ----------------------------------------------------------------------------------------
# Reading
# ----------------------------------------------------------------------------------------

class _Tokens:
    """The hierarchy's whitespace-separated tokens with their line numbers."""

    def __init__(self, path: Path, lines: list):
        self.path = path
        self.items = [(tok, n + 1) for n, line in enumerate(lines) for tok in line.split()]
        self.i = 0

    def line(self) -> int:
        return self.items[min(self.i, len(self.items) - 1)][1] if self.items else 1

    def next(self, what: str) -> str:
        if self.i >= len(self.items):
            raise BVHError(self.path, f"line {self.line()}: the file ends inside the HIERARCHY "
                                      f"(expected {what}); truncated?")
        tok = self.items[self.i][0]
        self.i += 1
        return tok

    def expect(self, word: str) -> None:
        tok = self.next(repr(word))
        if tok != word:
            self.i -= 1
            raise BVHError(self.path, f"line {self.line()}: expected {word!r}, found {tok!r}")

    def number(self, what: str, kind=float):
        tok = self.next(what)
        try:
            x = kind(tok)
        except ValueError:
            self.i -= 1
            raise BVHError(self.path, f"line {self.line()}: {what}: {tok!r} is not a number") from None
        if not math.isfinite(x):
            self.i -= 1
            raise BVHError(self.path, f"line {self.line()}: {what}: {tok!r} is not finite")
        return x


def _joint(tk: _Tokens, name: str, parent: int, out: dict) -> None:
    """Parse one joint's block (after its name) into ``out``, recursively."""
    j = len(out["joints"])
    if name in out["joints"]:
        raise BVHError(tk.path, f"line {tk.line()}: joint {name!r} is defined twice")
    out["joints"].append(name)
    out["parents"].append(parent)
    tk.expect("{")
    tk.expect("OFFSET")
    out["offsets"].append([tk.number(f"joint {name!r} OFFSET") for _ in range(3)])
    tk.expect("CHANNELS")
    n = tk.number(f"joint {name!r} CHANNELS count", int)
    chans = []
    for _ in range(n):
        c = tk.next(f"{n} channel names for joint {name!r}")
        if c not in POSITION and c not in ROTATION:
            raise BVHError(tk.path, f"line {tk.line()}: joint {name!r}: {c!r} is not a channel "
                                    f"(CHANNELS says {n}; expected names such as Zrotation)")
        chans.append(c)
    if len(set(chans)) != len(chans):
        raise BVHError(tk.path, f"line {tk.line()}: joint {name!r} repeats a channel {chans}")
    out["channels"].append(tuple(chans))
    while True:
        tok = tk.next(f"JOINT, End Site or '}}' closing joint {name!r}")
        if tok == "JOINT":
            _joint(tk, tk.next("a joint name"), j, out)
        elif tok == "End":
            tk.expect("Site")
            tk.expect("{")
            tk.expect("OFFSET")
            out["end_sites"][j] = [tk.number(f"End Site of {name!r}") for _ in range(3)]
            tk.expect("}")
        elif tok == "}":
            return
        else:
            tk.i -= 1
            raise BVHError(tk.path, f"line {tk.line()}: unexpected {tok!r} in joint {name!r}")


def _hierarchy(path: Path, lines: list) -> tuple:
    """The parsed hierarchy (dict) and the index of the line after 'Frame Time:'."""
    end = next((n for n, line in enumerate(lines) if line.split()[:1] == ["MOTION"]), len(lines))
    tk = _Tokens(path, lines[:end])
    tk.expect("HIERARCHY")
    tk.expect("ROOT")
    out = {"joints": [], "parents": [], "offsets": [], "channels": [], "end_sites": {}}
    _joint(tk, tk.next("the root's name"), -1, out)
    if tk.i < len(tk.items):
        raise BVHError(path, f"line {tk.items[tk.i][1]}: unexpected {tk.items[tk.i][0]!r} "
                             f"after the root joint (expected MOTION)")
    if end == len(lines):
        raise BVHError(path, f"line {len(lines)}: no MOTION section; truncated?")
    header = [(n, line.split()) for n, line in enumerate(lines[end + 1:end + 3], end + 1)]
    if (len(header) < 2 or header[0][1][:1] != ["Frames:"] or len(header[0][1]) != 2
            or header[1][1][:2] != ["Frame", "Time:"] or len(header[1][1]) != 3):
        raise BVHError(path, f"line {end + 2}: MOTION must be followed by 'Frames: F' and "
                             f"'Frame Time: dt' lines")
    try:
        out["frames"] = int(header[0][1][1])
        out["frame_time"] = float(header[1][1][2])
    except ValueError:
        raise BVHError(path, f"line {end + 2}: Frames or Frame Time is not a number") from None
    if out["frames"] < 1 or not out["frame_time"] > 0:
        raise BVHError(path, f"line {end + 2}: Frames must be ≥ 1 and Frame Time > 0")
    return out, end + 3


def _frames(path: Path, lines: list, start: int, h: dict) -> np.ndarray:
    """The F×C frame numbers, each line checked for its count and numbers."""
    labels = [(name, c) for name, chans in zip(h["joints"], h["channels"]) for c in chans]
    rows = [(n + 1, line.split()) for n, line in enumerate(lines[start:], start) if line.strip()]
    F, C = h["frames"], len(labels)
    if len(rows) < F:
        last = rows[-1][0] if rows else start
        raise BVHError(path, f"truncated: 'Frames: {F}' but only {len(rows)} frame lines "
                             f"(the file ends at line {last})")
    if len(rows) > F:
        raise BVHError(path, f"line {rows[F][0]}: more frame lines than 'Frames: {F}'")
    values = np.empty((F, C))
    for f, (n, toks) in enumerate(rows):
        if len(toks) != C:
            raise BVHError(path, f"line {n}: frame {f} has {len(toks)} values, the HIERARCHY "
                                 f"declares {C} channels")
        try:
            values[f] = [float(tok) for tok in toks]
        except ValueError:
            k = next(k for k, tok in enumerate(toks) if not _is_number(tok))
            raise BVHError(path, f"line {n}: value {k + 1} (joint {labels[k][0]!r} "
                                 f"{labels[k][1]}) {toks[k]!r} is not a number") from None
        bad = ~np.isfinite(values[f])
        if bad.any():
            k = int(np.argmax(bad))
            raise BVHError(path, f"line {n}: value {k + 1} (joint {labels[k][0]!r} "
                                 f"{labels[k][1]}) {toks[k]!r} is not finite")
    return values


def _is_number(tok: str) -> bool:
    try:
        float(tok)
    except ValueError:
        return False
    return True


def _local(h: dict, values: np.ndarray, scale: float):
    """Local rotations (F×J×3×3) and translations (F×J×3, metres) from the channels."""
    F, J = values.shape[0], len(h["joints"])
    R = np.broadcast_to(np.eye(3), (F, J, 3, 3)).copy()
    p = np.broadcast_to(np.asarray(h["offsets"], dtype=float) * scale, (F, J, 3)).copy()
    col = 0
    for j, chans in enumerate(h["channels"]):
        order, angles = "", []
        for c in chans:
            if c in POSITION:
                p[:, j, POSITION[c]] = values[:, col] * scale
            else:
                order += ROTATION[c]
                angles.append(values[:, col])
            col += 1
        if order:   # upper-case axes: intrinsic rotations, R = R_a1 R_a2 R_a3
            R[:, j] = Rotation.from_euler(order, np.stack(angles, -1), degrees=True).as_matrix()
    return R, p


def file_unit(joints, parents, offsets: np.ndarray) -> float:
    """Metres per file unit of a hierarchy (joint names, parent indices, OFFSETs J×3 in
    file units): :data:`CMU_UNIT` for CMU's joint names; else the first of :data:`UNITS`
    that puts the upper arm plus forearm of an arm found by its joints' names
    (:func:`tflearn.mocap.names.arm_chain`, right then left) within :data:`ARM_RANGE`;
    else centimetres."""
    if CMU_NAMES <= set(joints):
        return CMU_UNIT
    for side in ("right", "left"):
        try:
            _, elbow, wrist = names.arm_chain(joints, parents, side)
        except ValueError:
            continue
        arm = float(np.linalg.norm(offsets[elbow]) + np.linalg.norm(offsets[wrist]))
        lo, hi = ARM_RANGE
        return next((u for u in UNITS.values() if lo <= arm * u <= hi), CM)
    return CM


def read(path, scale: Optional[float] = None) -> Skeleton:
    """Read a BVH file (see the module doc). ``scale``: metres per file unit (None: read
    from the skeleton, :func:`file_unit`).
    Raises :class:`BVHError` naming the file, line and problem."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8", errors="strict")
    except (OSError, UnicodeDecodeError) as err:
        raise BVHError(path, f"cannot read the file ({type(err).__name__}: {err})") from None
    lines = re.split(r"\r\n|\r|\n", text)
    h, start = _hierarchy(path, lines)
    values = _frames(path, lines, start, h)
    if scale is None:
        scale = file_unit(h["joints"], h["parents"], np.asarray(h["offsets"], dtype=float))
    R, p = _local(h, values, scale)
    return Skeleton(name=path.stem, joints=tuple(h["joints"]), parents=tuple(h["parents"]),
                    offsets=np.asarray(h["offsets"], dtype=float) * scale,
                    channels=tuple(h["channels"]),
                    end_sites={j: np.asarray(o, dtype=float) * scale for j, o in h["end_sites"].items()},
                    frame_time=h["frame_time"], values=values, scale=float(scale),
                    rotations=R, positions=p, source=str(path))


# ----------------------------------------------------------------------------------------
# Writing
# ----------------------------------------------------------------------------------------

def channel_values(skel: Skeleton, rotations: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """Channel numbers (F×C, file units, degrees) that give local ``rotations`` (F×J×3×3)
    and ``positions`` (F×J×3, metres) in each joint's own channel order (components
    without a position channel are the OFFSET and are not written). At gimbal lock
    (middle angle ±90°) scipy sets the third angle to zero; the angles still give the
    rotation exactly."""
    cols = []
    for j, chans in enumerate(skel.channels):
        order = "".join(ROTATION[c] for c in chans if c in ROTATION)
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", "Gimbal lock", UserWarning)
            eul = (Rotation.from_matrix(rotations[:, j]).as_euler(order, degrees=True)
                   if order else None)
        k = 0
        for c in chans:
            if c in POSITION:
                cols.append(positions[:, j, POSITION[c]] / skel.scale)
            else:
                cols.append(eul[:, k])
                k += 1
    return np.stack(cols, -1)


def write(skel: Skeleton, path, values: Optional[np.ndarray] = None,
          frame_time: Optional[float] = None) -> None:
    """Write a skeleton's hierarchy and frames (``values`` F×C, default its own) as BVH,
    numbers with 10 significant digits, atomically."""
    values = skel.values if values is None else values
    frame_time = skel.frame_time if frame_time is None else frame_time
    children = {j: [k for k, p in enumerate(skel.parents) if p == j] for j in range(len(skel.joints))}
    out = ["HIERARCHY"]

    def block(j: int, depth: int) -> None:
        pad = "  " * depth
        out.append(f"{pad}{'ROOT' if depth == 0 else 'JOINT'} {skel.joints[j]}")
        out.append(f"{pad}{{")
        out.append(f"{pad}  OFFSET " + " ".join(f"{x / skel.scale:.10g}" for x in skel.offsets[j]))
        out.append(f"{pad}  CHANNELS {len(skel.channels[j])} " + " ".join(skel.channels[j]))
        for k in children[j]:
            block(k, depth + 1)
        if j in skel.end_sites:
            out.extend([f"{pad}  End Site", f"{pad}  {{",
                        f"{pad}    OFFSET " + " ".join(f"{x / skel.scale:.10g}" for x in skel.end_sites[j]),
                        f"{pad}  }}"])
        out.append(f"{pad}}}")

    block(0, 0)
    out += ["MOTION", f"Frames: {values.shape[0]}", f"Frame Time: {frame_time:.10g}"]
    out += [" ".join(f"{x:.10g}" for x in row) for row in values]
    with replacing(Path(path)) as tmp:
        Path(tmp).write_text("\n".join(out) + "\n")
