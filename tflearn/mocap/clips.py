"""Motion capture in and out: BVH clips → arm motions (.npz), the performer's body
(body.yaml), the torso's motion and a retargeting report; arm motions → BVH.

Import (:func:`import_clips`): each clip is read (:mod:`tflearn.mocap.bvh`), retargeted with
one shared shoulder chart (:mod:`tflearn.mocap.retarget`), smoothed only if its samples do
not resolve its torques, and resampled:

* resolution is judged at the native rate (:func:`tflearn.motions.spline.torque_resolution`,
  estimated relative torque error; resolved at ≤ 1%): upsampling a spline adds no
  information and would hide the problem;
* an unresolved clip is low-pass filtered, zero-phase (second-order Butterworth run
  forwards and backwards, :func:`scipy.signal.filtfilt`: |H|² of a 4th-order filter, no
  lag) on its unwrapped rotation vectors and hinge angle, with the highest cutoff of
  :attr:`ImportOptions.cutoffs` that resolves it (the report gives the cutoff, the
  resolution before and after, and the RMS change of the coordinates);
* the result is sampled at ``rate`` Hz on the quintic spline (velocities included).

Files written to ``out``: ``NAME.npz`` (the Motion format of :mod:`tflearn.motions.motion`),
``torso/NAME.npz`` (arrays t, R (T×3×3), x (T×3): the base frame — chest orientation at
the shoulder — in a z-up world, metres, at the clip's native frames, low-passed with
the arm's filter), ``body.yaml`` (a
train config's ``body:`` section: the arm preset with the clips' mean bone lengths and
the shared shoulder zero orientation) and ``report.json`` (with, per clip, how far and
fast the torso moved and how much its motion changes the arm's inverse-dynamics torques:
:func:`torso_torque_share`).
"""
from __future__ import annotations

import json
import math
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Mapping, Optional

import numpy as np
import roma
import torch
import yaml
from scipy.signal import butter, filtfilt

from ..errors import InputError
from ..io.files import write_text
from ..motions import motion as motion_mod
from ..motions import spline
from ..motions.torso import BaseMotion, Bases
from ..physics import dynamics
from ..physics.body import Body
from ..physics.configspace import align_quaternions, unwrap_rotvec, wrap_rotvec
from . import bvh
from . import retarget as rt

GRAVITY = (0.0, 0.0, -9.81)


@dataclass(frozen=True)
class ImportOptions:
    """Options of :func:`import_clips`.

    side: the performer's arm, "right", "left", or "moving": per clip the arm whose hand
    travels further relative to the chest (:func:`tflearn.mocap.retarget.moving_arm`);
    mirror: reflect the arms to the other side; clips: per clip (its file name without
    .bvh) a mapping with "arm" ("right" or "left") and "fps" (its true frame rate) that
    overrides side and fps. Every clip is brought onto one model arm
    (:attr:`model_side`): ``side``'s when all clips use it, else the right one, the other
    side with ``mirror``; a clip of the other arm is mirrored onto it.
    rate: output samples per second (None: each clip's own frame rate); fps: the clips'
    true frame rate when the header's is wrong (None: the header's); gravity: the body has
    gravity (else the thesis' gravity-free world); strict: stop at the first bad file
    (else skip it with a warning); cutoffs: low-pass cutoffs (Hz) tried, highest first;
    amap: the arm map for a skeleton without a built-in one (:class:`tflearn.mocap.retarget.
    ArmMap`); window: (start, stop) in seconds, the part of every clip kept (the arm's
    samples within it, times then from the first of them, and the torso's frames covering
    those; a clip shorter than stop is refused like a bad file), None: all of it;
    busiest: instead of a window, each clip's busiest this many seconds (the largest joint
    path length Σ‖Δν‖ at the output rate: :func:`busiest_window`); split: cut what is kept
    into consecutive pieces of this many seconds (rounded to whole samples), each its own
    motion NAME_partKK (pieces share their boundary samples; a remainder shorter than half
    a piece joins the last one), None: one motion per clip; like: a body (a ``body:``
    section, as :func:`like_body` reads it) whose shoulder chart and bones the clips are
    imported in (new clips for a trained run), None: the clips' own.
    """

    side: str = "right"
    mirror: bool = False
    clips: Mapping[str, Mapping] = field(default_factory=dict)
    rate: Optional[float] = None
    fps: Optional[float] = None
    gravity: bool = False
    strict: bool = False
    cutoffs: tuple = (12.0, 10.0, 8.0, 6.0, 5.0, 4.0, 3.0, 2.0)
    amap: Optional[rt.ArmMap] = None
    window: Optional[tuple] = None
    busiest: Optional[float] = None
    split: Optional[float] = None
    like: Optional[dict] = None

    def __post_init__(self):
        w = self.window
        if w is not None and not (len(w) == 2 and 0 <= w[0] < w[1]):
            raise InputError(f"a window is (start, stop) with 0 ≤ start < stop (seconds), got {tuple(w)}")
        for key, what in (("split", "a piece's length in seconds"), ("busiest", "a length in seconds"),
                          ("rate", "samples per second"), ("fps", "frames per second")):
            x = getattr(self, key)
            if x is not None and not x > 0:
                raise InputError(f"a {key} is {what} (> 0), got {x}")
        if w is not None and self.busiest is not None:
            raise InputError("a window and busiest both choose the part of a clip kept: give one")
        if self.side not in ("right", "left", "moving"):
            raise InputError(f"an arm is right, left or moving, got {self.side!r}")
        if self.like is not None and self.like.get("preset") != "arm":
            raise InputError(f"clips are imported like an arm (preset: arm), not {self.like}")
        if self.amap is not None and self.side == "moving":
            raise InputError("an arm map names one arm: give --arm right or left with it")
        for name, choice in self.clips.items():
            bad = set(choice) - {"arm", "fps"}
            if bad or choice.get("arm", "right") not in rt.OTHER or not choice.get("fps", 1.0) > 0:
                raise InputError(f"clip {name}: its choices are arm (right or left) and fps (> 0), "
                                 f"got {dict(choice)}")

    @property
    def model_side(self) -> str:
        """The arm every clip is imported onto (see the class doc)."""
        arms = {self.side, *(c.get("arm", self.side) for c in self.clips.values())}
        side = self.side if arms in ({"right"}, {"left"}) else "right"
        return rt.OTHER[side] if self.mirror else side

    def frames(self, skel: bvh.Skeleton) -> rt.ArmFrames:
        """A clip's arm with this import's per-clip choices: its frame rate, its arm, and
        mirrored when that arm is not :attr:`model_side`."""
        choice = self.clips.get(skel.name, {})
        fps = choice.get("fps", self.fps)
        if fps is not None:
            skel = replace(skel, frame_time=1.0 / fps)
        side = choice.get("arm", self.side)
        if side == "moving":
            side = rt.moving_arm(skel)
        return rt.arm_frames(skel, side, self.amap, side != self.model_side)


def _filtered(q: np.ndarray, fps: float, cutoff: float) -> np.ndarray:
    """Zero-phase low-pass of arm coordinates (T×7): rotation vectors unwrapped first."""
    b, a = butter(2, cutoff / (fps / 2.0))
    x = q.copy()
    for s in (slice(0, 3), slice(4, 7)):
        x[:, s] = unwrap_rotvec(torch.from_numpy(q[:, s])).numpy()
    x = np.ascontiguousarray(filtfilt(b, a, x, axis=0))
    for s in (slice(0, 3), slice(4, 7)):
        x[:, s] = wrap_rotvec(torch.from_numpy(x[:, s])).numpy()
    return x


def smooth(m: motion_mod.Motion, cutoffs) -> tuple:
    """The motion, low-passed with the highest cutoff that resolves its torques at its
    own rate (unchanged when already resolved), and the filter report."""
    eps = spline.torque_resolution(m.body, m)
    report = {"resolution_native": eps, "cutoff_hz": None, "resolution_smoothed": eps,
              "change_rms_rad": 0.0}
    if not eps > spline.RESOLVED:
        return m, report
    q = m.q.numpy()
    for fc in [c for c in cutoffs if c < m.rate / 2]:
        x = _filtered(q, m.rate, fc)
        sm = motion_mod.Motion(m.name, m.t, x, None, m.body)
        e = spline.torque_resolution(m.body, sm)
        report.update(cutoff_hz=fc, resolution_smoothed=e,
                      change_rms_rad=float(np.sqrt(((x - q) ** 2).mean())))
        if e <= spline.RESOLVED:
            return sm, report
    return sm, report


def torso_torque_share(body: Body, m: motion_mod.Motion, base: BaseMotion) -> float:
    """‖τ_moving − τ_fixed‖ / ‖τ_fixed‖ over the motion's samples: how much the torso's
    motion changes the arm's inverse-dynamics torques (spline ν, ω, ω̇ of the motion;
    RNEA with and without the base terms of :mod:`tflearn.motions.torso`)."""
    q, v, a, rots = spline.MotionSpline(body, m)(m.t)
    fixed = dynamics.rnea_rot(body, rots, q, v, a)
    t = torch.as_tensor(m.t, dtype=torch.float64)
    g, b = Bases.of([base]).take(torch.zeros(len(t), dtype=torch.long)).terms(body.gravity, t)
    moving = dynamics.rnea_rot(body, rots, q, v, a, gravity=g, base=b)
    return float((moving - fixed).norm() / fixed.norm().clamp_min(1e-12))


def _body_doc(frames: list, zero: np.ndarray, gravity: bool) -> dict:
    lengths = np.mean([f.lengths for f in frames], axis=0)
    return {"preset": "arm", "lengths": [round(float(x), 6) for x in lengths],
            "offsets": [[float(x) for x in zero], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]],
            "gravity": list(GRAVITY) if gravity else [0.0, 0.0, 0.0]}


def import_clips(paths, out, options: ImportOptions = ImportOptions(), *, choices: bool = True) -> dict:
    """Import BVH files and folders into ``out`` (see the module doc). Returns the report
    (also written as report.json): per clip the retargeting report (:func:`tflearn.
    retarget.retarget`), the filter, the torso's motion and the file written. With
    ``choices``, per-clip choices naming no clip imported are warned about (a typo)."""
    frames = rt.read_clips(paths, options.frames, options.strict)
    names = {f.skeleton.name for f in frames}
    for name in sorted(set(options.clips) - names if choices else ()):
        warnings.warn(f"clip {name}: has choices but is not among the clips imported "
                      f"({', '.join(sorted(names))})", rt.BVHWarning, stacklevel=2)
    return import_frames(frames, out, options)


def import_frames(frames: list, out, options: ImportOptions = ImportOptions()) -> dict:
    """:func:`import_clips` of clips already read (:class:`tflearn.mocap.retarget.ArmFrames`,
    of any sides and mirrors: one shoulder chart and one body for all, or ``options.like``'s).
    An earlier import into ``out`` is added to when this one is in its body (``like``
    it), replaced when this one re-imports all its clips, and refused otherwise
    (:func:`_earlier`)."""
    from ..physics.body import from_config
    if not frames:
        raise InputError(f"{out}: no clips to import")
    names = [f.skeleton.name + ("_mirrored" if f.mirror else "") for f in frames]
    if len(set(names)) != len(names):
        raise InputError(f"{out}: two clips have the same name ({sorted(names)})")
    if options.like is None:
        zero = rt.shoulder_zero(frames)
        doc = _body_doc(frames, zero, options.gravity)
    else:
        doc, zero = options.like, np.asarray(options.like.get("offsets", [[0.0] * 3])[0], dtype=float)
    body = from_config(doc)
    out = Path(out)
    kept, dropped = _earlier(out, doc, names)
    out.mkdir(parents=True, exist_ok=True)
    clips = []
    for r in rt.retarget_all(frames, zero):
        m = motion_mod.Motion(r.motion.name, r.motion.t, r.motion.q, None, body)
        if not _long_enough(m, options):
            continue
        sm, filt = smooth(m, options.cutoffs)
        rate = options.rate or m.rate
        sampled = spline.resample(sm, rate)
        window = options.window if options.busiest is None else busiest_window(sampled, options.busiest)
        (out / "torso").mkdir(exist_ok=True)      # here: no empty folder when no clip fits
        for final, span in _pieces(sampled, window, options.split):
            motion_mod.save(final, out / f"{final.name}.npz")
            base = _save_torso(r.frames, out / "torso" / f"{final.name}.npz", filt["cutoff_hz"], span)
            torso = {**r.report["torso"], "torque_share": torso_torque_share(body, final, base)}
            clips.append({**r.report, "torso": torso, "filter": filt, "rate_hz": rate,
                          "window_s": None if span is None else list(span), "file": f"{final.name}.npz"})
    if not clips:
        raise InputError(f"{out}: no clip is as long as the window "
                         f"{list(options.window) if options.busiest is None else options.busiest} s")
    written = {c["file"] for c in clips}
    _remove(out, [c for c in dropped if c["file"] not in written])
    side = ", ".join(sorted({("mirrored " if f.mirror else "") + f.side for f in frames}))
    origin = (f"from {len(frames)} BVH clip(s): mean bone lengths (m),\n# the shoulder zero orientation "
              f"shared by the clips (a rotation vector)." if options.like is None else
              "in the body and shoulder chart the clips were imported like (--like).")
    if not _holds_body(out / "body.yaml", doc):              # an import added to keeps its own
        write_text(out / "body.yaml", f"# The performer's arm ({side}) {origin}\n"
                   + yaml.safe_dump({"body": doc}, default_flow_style=None, sort_keys=False))
    report = {"sides": side, "gravity": bool(any(doc.get("gravity", [0.0]))),
              "shoulder_zero": [float(x) for x in zero], "body": doc, "clips": kept + clips}
    write_text(out / "report.json", json.dumps(report, indent=2) + "\n")
    return {**report, "clips": clips}


def _body_in(path: Path) -> Optional[dict]:
    """The ``body:`` section of a YAML file (a body.yaml, a run's config.yaml), None when
    the file is absent or holds none; errors reading it name the file."""
    from ..config import read
    doc = read(path).get("body") if path.exists() else None
    return doc if isinstance(doc, dict) else None


def _holds_body(path: Path, doc: dict) -> bool:
    held = _body_in(path)
    return held is not None and same_body(held, doc)


def _clip_key(entry: dict) -> str:
    return entry["clip"] + ("_mirrored" if entry["mirrored"] else "")


def same_body(a: dict, b: dict) -> bool:
    """Whether two ``body:`` sections make the same body (its kinematics and inertia)."""
    from ..physics.body import from_config
    return from_config(a).to_dict() == from_config(b).to_dict()


def _earlier(out: Path, doc: dict, names: list) -> tuple:
    """(kept, dropped): the report entries of an earlier import into ``out`` that an
    import of clips ``names`` in body ``doc`` keeps, and those it replaces (their files
    are removed unless written again: a clip imported whole after being split leaves no
    pieces behind). With the same body it keeps the other clips; with another body it
    keeps none when it holds all their clips, and otherwise raises :class:`InputError`
    (the new chart would silently move the earlier clips' coordinates)."""
    path = out / "report.json"
    if not path.exists():
        return [], []
    old = json.loads(path.read_text())
    mine = [c for c in old["clips"] if _clip_key(c) in names]
    if same_body(old["body"], doc):
        return [c for c in old["clips"] if _clip_key(c) not in names], mine
    if len(mine) == len(old["clips"]):
        return [], mine
    others = sorted({_clip_key(c) for c in old["clips"]} - set(names))
    raise InputError(f"{out}: holds an import of other clips ({', '.join(others)}) in another body "
                     f"or shoulder chart; import into another folder, or add these clips in its "
                     f"chart with --like {out}")


def _remove(out: Path, entries: list) -> None:
    for c in entries:
        for f in (out / c["file"], out / "torso" / c["file"]):
            f.unlink(missing_ok=True)


def like_body(path) -> dict:
    """The ``body:`` section that clips are imported like (``--like``): of a run folder
    (its config.yaml), an import folder (its body.yaml) or a YAML file holding one; an
    arm (preset "arm"). :class:`InputError` names the path and the problem."""
    path = Path(path)
    if path.is_dir():
        found = [path / n for n in ("config.yaml", "body.yaml") if (path / n).exists()]
        if not found:
            raise InputError(f"{path}: neither a run (config.yaml) nor an import (body.yaml)")
        path = found[0]
    doc = _body_in(path)
    if doc is None or doc.get("preset") != "arm":
        raise InputError(f"{path}: its body: section is not an arm (preset: arm), got {doc!r}")
    return doc


def chart_angle(a: dict, b: dict) -> float:
    """The angle (degrees) between the shoulder charts (zero orientations) of two arm bodies."""
    from scipy.spatial.transform import Rotation
    za, zb = (Rotation.from_rotvec(np.asarray(d.get("offsets", [[0.0] * 3])[0], dtype=float))
              for d in (a, b))
    return float(np.degrees((za.inv() * zb).magnitude()))


def busiest_window(m: motion_mod.Motion, seconds: float) -> tuple:
    """(start, stop) in seconds: the window of ``seconds`` (rounded to whole samples) of
    ``m`` (uniformly sampled) with the largest joint path length Σ‖Δν‖."""
    n = max(1, round(seconds * m.rate))
    step = np.linalg.norm(np.diff(m.q.numpy(), axis=0), axis=1)
    i = int(np.argmax(np.convolve(step, np.ones(n), mode="valid")))
    return float(m.t[i]), float(m.t[i + n])


def _items(data) -> list:
    """A config's ``data`` as a list of the paths it names (one, or several)."""
    return [data] if isinstance(data, (str, Path)) else list(data)


def bvh_paths(data) -> list:
    """The BVH clips a train config's ``data`` names: .bvh files and folders holding
    .bvh files (as :class:`~pathlib.Path`); [] when it names none. Raises
    :class:`InputError` when it mixes them with motion files, or a folder holds both."""
    items = _items(data)
    if [str(x) for x in items] == ["gestures"]:
        return []
    paths = [Path(x) for x in items]
    clips = []
    for p in paths:
        if p.is_dir() and any(p.glob("*.bvh")):
            if any(p.glob("*.npz")):
                raise InputError(f"{p}: holds both BVH clips and .npz motions; "
                                 f"name the clips or the motions, not the folder")
            clips.append(p)
        elif p.suffix.lower() == ".bvh":
            clips.append(p)
    if clips and len(clips) != len(paths):
        others = [str(p) for p in paths if p not in clips]
        raise InputError(f"data: names BVH clips and motion files together ({', '.join(others)}); "
                         f"import the clips first (tflearn bvh import) or name only clips")
    return clips


def import_options(bvh, strict: bool = False, like: Optional[dict] = None) -> ImportOptions:
    """A config's ``bvh:`` section (:class:`tflearn.config.BvhSection`) as the options of
    :func:`import_clips`, with ``strict`` and ``like``."""
    clips = {name: c.model_dump(exclude_none=True) for name, c in bvh.clips.items()}
    return ImportOptions(side=bvh.arm, mirror=bvh.mirror, clips=clips, rate=bvh.rate, strict=strict,
                         window=None if bvh.window is None else tuple(bvh.window),
                         busiest=bvh.busiest, split=bvh.split, like=like)


def import_config(cfg):
    """A train config (:class:`tflearn.config.Config`) whose ``data`` names BVH clips
    (:func:`bvh_paths`), with the clips imported (:func:`import_clips`, the config's
    ``bvh`` options and ``strict``) into OUT/imported: returned with ``data`` that folder
    and ``body`` the performer's arm from the import. A config whose own ``body`` is not
    the default arm is warned about, naming the section replaced; a config naming no
    clips is returned as it is. Returns (config, import report or None)."""
    clips = bvh_paths(cfg.data)
    if not clips:
        return cfg, None
    out = Path(cfg.out) / "imported"
    report = import_clips(clips, out, import_options(cfg.bvh, cfg.strict))
    if cfg.body not in ({"preset": "arm"}, report["body"]):
        warnings.warn(f"{cfg.out}: the config's body: section is replaced by the performer's arm "
                      f"imported from the BVH clips ({out / 'body.yaml'})", stacklevel=2)
    return cfg.replace(data=str(out), body=report["body"]), report


def import_like(cfg, data, out) -> Optional[Path]:
    """Clips a trained run has not seen, brought into its body and chart: when ``data``
    names BVH clips (:func:`bvh_paths`), they are imported into ``out`` with the run's
    config's ``bvh`` choices (those of its clips) like its body (``cfg``: the run's config), and that folder
    is returned; when it is a folder of motions with a body.yaml that is not the run's
    body, :class:`InputError` says so (their coordinates would be read in the wrong chart);
    else None (``data`` is read as it is)."""
    clips = bvh_paths(data)
    if clips:
        import_clips(clips, out, import_options(cfg.bvh, cfg.strict, like=cfg.body), choices=False)
        return Path(out)
    items = _items(data)
    for folder in {Path(x) if Path(x).is_dir() else Path(x).parent for x in items}:
        path = folder / "body.yaml"
        doc = _body_in(path)
        if doc is not None and not same_body(doc, cfg.body):
            raise InputError(
                f"{path}: these motions are not in the run's body (shoulder chart "
                f"{chart_angle(doc, cfg.body):.1f}° from the run's, bones "
                f"{doc.get('lengths')} against {cfg.body.get('lengths')}); import their clips in "
                f"the run's chart (tflearn bvh import CLIPS --like RUN), or name the clips")
    return None


def _long_enough(m: motion_mod.Motion, options: ImportOptions) -> bool:
    """Whether clip ``m`` covers ``options.window`` (or lasts ``options.busiest``); if
    not, raises :class:`InputError` naming it (``strict``) or warns and returns False."""
    need = options.busiest if options.window is None else options.window[1]
    if need is None or need <= float(m.t[-1]) + 1e-9:
        return True
    what = f"{options.busiest} s" if options.window is None else f"the window {list(options.window)} s"
    msg = f"{m.name}: {what} ends after the clip ({float(m.t[-1]):.2f} s long)"
    if options.strict:
        raise InputError(msg)
    warnings.warn(msg + "; skipped", rt.BVHWarning, stacklevel=3)
    return False


def _cut(m: motion_mod.Motion, window: tuple, name: Optional[str] = None) -> tuple:
    """(the samples of ``m`` with start ≤ t ≤ stop, times from the first of them, named
    ``name`` (default ``m``'s); the clip times (first, last) kept)."""
    keep = (m.t >= window[0] - 1e-9) & (m.t <= window[1] + 1e-9)
    t = m.t[keep]
    span = (float(t[0]), float(t[-1]))
    return motion_mod.Motion(name or m.name, t - t[0], m.q[keep], m.qd[keep], m.body), span


def _pieces(m: motion_mod.Motion, window: Optional[tuple], split: Optional[float]) -> list:
    """[(motion, clip times (first, last) or None)]: ``m`` (uniformly sampled) cut to
    ``window`` and then into pieces of round(``split``·rate) sample intervals
    (:class:`ImportOptions`); both None: [(``m``, None)]."""
    if window is None and split is None:
        return [(m, None)]
    whole, span = _cut(m, window if window is not None else (0.0, float(m.t[-1])))
    if split is None:
        return [(whole, span)]
    n, last = max(1, round(split * m.rate)), whole.T - 1
    count = max(1, math.floor(last / n + 0.5))              # a remainder < n/2 joins the last
    bounds = [k * n for k in range(count)] + [last]
    pieces = []
    for k, (a, b) in enumerate(zip(bounds, bounds[1:])):
        ta, tb = float(whole.t[a]), float(whole.t[b])
        piece, _ = _cut(whole, (ta, tb), f"{m.name}_part{k:02d}")
        pieces.append((piece, (span[0] + ta, span[0] + tb)))           # clip times
    return pieces


def _save_torso(frames: rt.ArmFrames, path: Path, cutoff: Optional[float],
                span: Optional[tuple] = None) -> BaseMotion:
    """Write the base frame in the z-up model world (BVH world rotated by Pᵀ), low-passed
    like the arm (``cutoff`` Hz; positions and sign-aligned quaternions, renormalised);
    with ``span`` (the clip times (first, last) of a windowed arm motion) only the frames
    covering it, one frame beyond each end, times from its first; return it."""
    from ..io.files import replacing
    fps = 1.0 / frames.skeleton.frame_time
    t = np.arange(frames.skeleton.frames) / fps
    R = rt.P.T @ frames.base_R
    x = frames.base_x @ rt.P                          # (Pᵀ x) for row vectors
    if cutoff is not None:
        b, a = butter(2, cutoff / (fps / 2.0))
        quat = align_quaternions(roma.rotmat_to_unitquat(torch.from_numpy(R))).numpy()
        quat = np.ascontiguousarray(filtfilt(b, a, quat, axis=0))
        R = roma.unitquat_to_rotmat(roma.quat_normalize(torch.from_numpy(quat))).numpy()
        x = np.ascontiguousarray(filtfilt(b, a, x, axis=0))
    if span is not None:
        keep = (t >= span[0] - 1.0 / fps) & (t <= span[1] + 1.0 / fps)
        t, R, x = t[keep] - span[0], R[keep], x[keep]
    with replacing(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, t=t, R=R, x=x)
    return BaseMotion(t, R, x)


def by_clip(report: dict) -> list:
    """The entries of ``report["clips"]`` grouped by clip (a split clip's pieces together,
    in order): a list of lists."""
    clips = {}
    for c in report["clips"]:
        clips.setdefault((c["clip"], c["mirrored"]), []).append(c)
    return list(clips.values())


def torque_share_text(pieces: list) -> str:
    """How much the torso changes the arm's torques, as text: "N%", or "N–M%" over the
    pieces of a split clip (entries of ``report["clips"]``)."""
    shares = [100 * p["torso"]["torque_share"] for p in pieces]
    return f"{shares[0]:.0f}%" if len(shares) == 1 else f"{min(shares):.0f}–{max(shares):.0f}%"


def report_lines(report: dict) -> list:
    """One printed line per clip (the pieces of a split clip together)."""
    lines = []
    for pieces in by_clip(report):
        c = pieces[0]
        f, pe, tor = c["filter"], c["position_error_m"], c["torso"]
        cut = f"; cut into {len(pieces)} pieces" if len(pieces) > 1 else ""
        filt = ("unfiltered" if f["cutoff_hz"] is None else
                f"low-pass {f['cutoff_hz']:g} Hz (changed {math.degrees(f['change_rms_rad']):.2f}° RMS)")
        lines.append(
            f"{c['clip']:>42s}: {c['frames']} frames at {c['fps']:.0f} fps; hinge loses "
            f"{c['hinge_lost_deg']['rms']:.2f}° RMS ({c['hinge_lost_deg']['max']:.2f}° max), twist "
            f"{c['forearm_twist_deg']['rms']:.0f}° RMS into the wrist; shoulder ≤ "
            f"{c['shoulder_angle_max_deg']:.0f}°; elbow/wrist within {1000 * pe['elbow_max']:.2f}/"
            f"{1000 * pe['wrist_max']:.2f} mm; torque resolution {100 * f['resolution_native']:.2f}% → "
            f"{100 * f['resolution_smoothed']:.2f}% ({filt}); torso moved {100 * tor['travel_m']:.0f} cm, "
            f"≤ {tor['speed_max_m_s']:.2f} m/s, turned ≤ {tor['rotation_max_deg']:.0f}°, changing the "
            f"arm's torques by {torque_share_text(pieces)}{cut}")
    return lines


# ----------------------------------------------------------------------------------------
# Export
# ----------------------------------------------------------------------------------------

def export(body: Body, t: np.ndarray, q: np.ndarray, out, skeleton=None, side: str = "right",
           mirror: bool = False) -> Path:
    """Write an arm motion (times t uniform, coordinates q T×7) as BVH: the arm alone
    (:func:`tflearn.mocap.retarget.arm_skeleton`), or, with ``skeleton`` (a BVH file), that
    skeleton with its ``side`` arm (``mirror``: the motion is the mirrored arm's) moved
    by the motion (:func:`tflearn.mocap.retarget.replace_arm`)."""
    out = Path(out)
    if skeleton is None:
        skel = rt.arm_skeleton(body, t, q, name=out.stem)
    else:
        frames = rt.arm_frames(bvh.read(skeleton), side, None, mirror)
        skel = rt.replace_arm(frames, body, t, q)
    bvh.write(skel, out)
    return out
