"""Motion capture in and out: BVH clips → arm motions (.npz), the performer's body
(body.yaml), the torso's motion and a retargeting report; arm motions → BVH.

Import (:func:`import_clips`): each clip is read (:mod:`tflearn.bvh`), retargeted with
one shared shoulder chart (:mod:`tflearn.retarget`), smoothed only if its samples do
not resolve its torques, and resampled:

* resolution is judged at the native rate (:func:`tflearn.motion.torque_resolution`,
  estimated relative torque error; resolved at ≤ 1%): upsampling a spline adds no
  information and would hide the problem;
* an unresolved clip is low-pass filtered, zero-phase (second-order Butterworth run
  forwards and backwards, :func:`scipy.signal.filtfilt`: |H|² of a 4th-order filter, no
  lag) on its unwrapped rotation vectors and hinge angle, with the highest cutoff of
  :attr:`ImportOptions.cutoffs` that resolves it (the report gives the cutoff, the
  resolution before and after, and the RMS change of the coordinates);
* the result is sampled at ``rate`` Hz on the quintic spline (velocities included).

Files written to ``out``: ``NAME.npz`` (the Motion format of :mod:`tflearn.motion`),
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
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
import roma
import torch
import yaml
from scipy.signal import butter, filtfilt

from . import bvh, dynamics
from . import motion as motion_mod
from . import retarget as rt
from .body import Body
from .configspace import align_quaternions, unwrap_rotvec, wrap_rotvec
from .errors import InputError
from .io.files import write_text
from .simulate import base_terms
from .torso import BaseMotion

GRAVITY = (0.0, 0.0, -9.81)


@dataclass(frozen=True)
class ImportOptions:
    """Options of :func:`import_clips`.

    side: the performer's arm, "right" or "left"; mirror: reflect it to the other side;
    rate: output samples per second; fps: the clips' true frame rate when the header's
    is wrong (None: the header's); gravity: the body has gravity (else the thesis'
    gravity-free world); strict: stop at the first bad file (else skip it with a
    warning); cutoffs: low-pass cutoffs (Hz) tried, highest first.
    """

    side: str = "right"
    mirror: bool = False
    rate: float = 120.0
    fps: Optional[float] = None
    gravity: bool = False
    strict: bool = False
    cutoffs: tuple = (12.0, 10.0, 8.0, 6.0, 5.0, 4.0, 3.0, 2.0)


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
    eps = motion_mod.torque_resolution(m.body, m)
    report = {"resolution_native": eps, "cutoff_hz": None, "resolution_smoothed": eps,
              "change_rms_rad": 0.0}
    if not eps > motion_mod.RESOLVED:
        return m, report
    q = m.q.numpy()
    for fc in [c for c in cutoffs if c < m.rate / 2]:
        x = _filtered(q, m.rate, fc)
        sm = motion_mod.Motion(m.name, m.t, x, None, m.body)
        e = motion_mod.torque_resolution(m.body, sm)
        report.update(cutoff_hz=fc, resolution_smoothed=e,
                      change_rms_rad=float(np.sqrt(((x - q) ** 2).mean())))
        if e <= motion_mod.RESOLVED:
            return sm, report
    return sm, report


def torso_torque_share(body: Body, m: motion_mod.Motion, base: BaseMotion) -> float:
    """‖τ_moving − τ_fixed‖ / ‖τ_fixed‖ over the motion's samples: how much the torso's
    motion changes the arm's inverse-dynamics torques (spline ν, ω, ω̇ of the motion;
    RNEA with and without the base terms of :mod:`tflearn.torso`)."""
    q, v, a, rots = motion_mod.MotionSpline(body, m)(m.t)
    fixed = dynamics.rnea_rot(body, rots, q, v, a)
    terms = [base_terms(body, base, float(t)) for t in m.t]
    g = torch.stack([x[0] for x in terms])
    b = tuple(torch.stack([x[1][k] for x in terms]) for k in range(3))
    moving = dynamics.rnea_rot(body, rots, q, v, a, gravity=g, base=b)
    return float((moving - fixed).norm() / fixed.norm().clamp_min(1e-12))


def _body_doc(frames: list, zero: np.ndarray, gravity: bool) -> dict:
    lengths = np.mean([f.lengths for f in frames], axis=0)
    return {"preset": "arm", "lengths": [round(float(x), 6) for x in lengths],
            "offsets": [[float(x) for x in zero], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]],
            "gravity": list(GRAVITY) if gravity else [0.0, 0.0, 0.0]}


def import_clips(paths, out, options: ImportOptions = ImportOptions()) -> dict:
    """Import BVH files and folders into ``out`` (see the module doc). Returns the report
    (also written as report.json): per clip the retargeting report (:func:`tflearn.
    retarget.retarget`), the filter, the torso's motion and the file written."""
    frames = rt.read_clips(paths, options.side, options.mirror, options.strict)
    if options.fps is not None:
        frames = [rt.arm_frames(_with_fps(f.skeleton, options.fps), options.side, None, options.mirror)
                  for f in frames]
    return import_frames(frames, out, options)


def import_frames(frames: list, out, options: ImportOptions = ImportOptions()) -> dict:
    """:func:`import_clips` of clips already read (:class:`tflearn.retarget.ArmFrames`,
    of any sides and mirrors: one shoulder chart and one body for all)."""
    from .body import from_config
    names = [f.skeleton.name + ("_mirrored" if f.mirror else "") for f in frames]
    if len(set(names)) != len(names):
        raise InputError(f"{out}: two clips have the same name ({sorted(names)})")
    zero = rt.shoulder_zero(frames)
    doc = _body_doc(frames, zero, options.gravity)
    body = from_config(doc)
    out = Path(out)
    (out / "torso").mkdir(parents=True, exist_ok=True)
    clips = []
    for r in rt.retarget_all(frames, zero):
        m = motion_mod.Motion(r.motion.name, r.motion.t, r.motion.q, None, body)
        sm, filt = smooth(m, options.cutoffs)
        final = motion_mod.resample(sm, options.rate)
        motion_mod.save(final, out / f"{m.name}.npz")
        base = _save_torso(r.frames, out / "torso" / f"{m.name}.npz", filt["cutoff_hz"])
        r.report["torso"]["torque_share"] = torso_torque_share(body, final, base)
        clips.append({**r.report, "filter": filt, "rate_hz": options.rate,
                      "file": f"{m.name}.npz"})
    side = ", ".join(sorted({("mirrored " if f.mirror else "") + f.side for f in frames}))
    write_text(out / "body.yaml",
               f"# The performer's arm ({side}) from {len(frames)} BVH clip(s): mean bone lengths (m),\n"
               f"# the shoulder zero orientation shared by the clips (a rotation vector).\n"
               + yaml.safe_dump({"body": doc}, default_flow_style=None, sort_keys=False))
    report = {"sides": side, "gravity": options.gravity,
              "shoulder_zero": [float(x) for x in zero], "body": doc, "clips": clips}
    write_text(out / "report.json", json.dumps(report, indent=2) + "\n")
    return report


def _with_fps(skel: bvh.Skeleton, fps: float) -> bvh.Skeleton:
    from dataclasses import replace
    if not fps > 0:
        raise InputError(f"--fps must be positive, got {fps}")
    return replace(skel, frame_time=1.0 / fps)


def _save_torso(frames: rt.ArmFrames, path: Path, cutoff: Optional[float]) -> BaseMotion:
    """Write the base frame in the z-up model world (BVH world rotated by Pᵀ), low-passed
    like the arm (``cutoff`` Hz; positions and sign-aligned quaternions, renormalised);
    return it."""
    from .io.files import replacing
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
    with replacing(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, t=t, R=R, x=x)
    return BaseMotion(t, R, x)


def report_lines(report: dict) -> list:
    """One printed line per clip."""
    lines = []
    for c in report["clips"]:
        f, pe, tor = c["filter"], c["position_error_m"], c["torso"]
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
            f"arm's torques by {100 * tor['torque_share']:.0f}%")
    return lines


# ----------------------------------------------------------------------------------------
# Export
# ----------------------------------------------------------------------------------------

def export(body: Body, t: np.ndarray, q: np.ndarray, out, skeleton=None, side: str = "right",
           mirror: bool = False) -> Path:
    """Write an arm motion (times t uniform, coordinates q T×7) as BVH: the arm alone
    (:func:`tflearn.retarget.arm_skeleton`), or, with ``skeleton`` (a BVH file), that
    skeleton with its ``side`` arm (``mirror``: the motion is the mirrored arm's) moved
    by the motion (:func:`tflearn.retarget.replace_arm`)."""
    out = Path(out)
    if skeleton is None:
        skel = rt.arm_skeleton(body, t, q, name=out.stem)
    else:
        frames = rt.arm_frames(bvh.read(skeleton), side, None, mirror)
        skel = rt.replace_arm(frames, body, t, q)
    bvh.write(skel, out)
    return out
