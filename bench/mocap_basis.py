"""One shared basis over recorded arm movements (left arms mirrored): import the clips
of the mocap folder, each clip's busiest window, train configs/mocap.yaml on
the windows, and print per window the joint RMSE, the maximum hand-tip error, M and the
wall time. ``--whole`` learns every clip whole instead, cut into consecutive pieces of
the window's length (``tflearn bvh import --split``), each piece a motion.

    PYTHONPATH=. python bench/mocap_basis.py [--mocap DIR] [--out runs/mocap_bench]
        [--window 1.0] [--whole] [--clips TEXT...] [--import-only] [key=value ...]   (config overrides)

``torso=moving`` trains each window on its performer's moving torso (docs/mocap.md).
Under ``torchrun --standalone --nproc-per-node N bench/mocap_basis.py ...`` rank 0
imports and the ranks train together (docs/parallel.md).

``--import-only`` prints the retargeting report of the import as a markdown table and
stops (the table in docs/mocap.md).

The mocap folder defaults to $TFLEARN_MOCAP, else ../shared/data/mocap beside the
repository. The clips are imported with configs/mocap.yaml's ``bvh`` choices: per clip
the arm that moves (left ones mirrored), the CMU clip at 60 fps (its header says 120; see
the data README). ``train configs/mocap.yaml`` alone is the busiest 0.8 s at 50 Hz.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tflearn import config, parallel, train  # noqa: E402
from tflearn.mocap import clips as mocap  # noqa: E402
from tflearn.physics.body import from_config  # noqa: E402


def import_table(report: dict) -> str:
    """The retargeting report as a markdown table, one row per clip."""
    rows = ["| clip | arm | fps | hinge lost RMS / max (°) | twist into wrist RMS / max (°) | "
            "shoulder max (°) | elbow / wrist error (mm) | torque resolution native → smoothed "
            "(cutoff) | torso travel (cm) / speed (m/s) / turn (°) / torque change |",
            "|---|---|---:|---|---|---:|---|---|---|"]
    for pieces in mocap.by_clip(report):            # the pieces of a clip (--whole) on one row
        c = pieces[0]
        f, pe, t = c["filter"], c["position_error_m"], c["torso"]
        cut = "none" if f["cutoff_hz"] is None else f"{f['cutoff_hz']:g} Hz"
        rows.append(
            f"| {c['clip']} | {('mirrored ' if c['mirrored'] else '') + c['side']} | {c['fps']:.0f} | "
            f"{c['hinge_lost_deg']['rms']:.3f} / {c['hinge_lost_deg']['max']:.3f} | "
            f"{c['forearm_twist_deg']['rms']:.1f} / {c['forearm_twist_deg']['max']:.1f} | "
            f"{c['shoulder_angle_max_deg']:.0f} | "
            f"{1000 * pe['elbow_max']:.4f} / {1000 * pe['wrist_max']:.3f} | "
            f"{100 * f['resolution_native']:.2f}% → {100 * f['resolution_smoothed']:.2f}% ({cut}) | "
            f"{100 * t['travel_m']:.0f} / {t['speed_max_m_s']:.2f} / {t['rotation_max_deg']:.0f} / "
            f"{mocap.torque_share_text(pieces)} |")
    return "\n".join(rows)


def clip_summary(report: dict, rows: dict) -> dict:
    """{clip: pieces, reproduced (how many), rmse (root mean square over its pieces), tip
    (the largest)} from the pieces' rows of metrics.json's motions (a piece's motion is
    its clip's name with _partKK)."""
    pieces = {}
    for c in report["clips"]:
        name = c["file"][:-4]
        pieces.setdefault(name.rsplit("_part", 1)[0], []).append(rows[name])
    return {clip: {"pieces": len(rs), "reproduced": sum(bool(r["success"]) for r in rs),
                   "rmse": float(np.sqrt(np.mean([r["rmse"] ** 2 for r in rs]))),
                   "tip": max(r["tip"] for r in rs)} for clip, rs in pieces.items()}


def arguments(description: str) -> argparse.ArgumentParser:
    """The options shared with bench/mocap_dmp.py."""
    p = argparse.ArgumentParser(description=description)
    default = os.environ.get("TFLEARN_MOCAP") or str(ROOT.parent / "shared" / "data" / "mocap")
    p.add_argument("--mocap", type=Path, default=Path(default))
    p.add_argument("--out", type=Path, default=ROOT / "runs" / "mocap_bench")
    p.add_argument("--window", type=float, default=1.0, help="window length, seconds")
    p.add_argument("--clips", nargs="*", default=None,
                   help="use only the clips whose names contain one of these strings (default: all)")
    p.add_argument("--rate", type=float, default=60.0, help="window sampling rate, Hz")
    p.add_argument("--whole", action="store_true",
                   help="every clip whole, cut into consecutive pieces of --window seconds")
    return p


def prepare_windows(args) -> tuple:
    """Import the clips with configs/mocap.yaml's ``bvh`` choices (each clip's arm, the
    CMU clip's true rate) at --rate: each clip's busiest --window seconds into OUT/windows,
    or with --whole every clip cut into pieces of that length into OUT/pieces; returns
    (report, body, folder)."""
    files = sorted(args.mocap.glob("*.bvh"))
    if args.clips:
        files = [f for f in files if any(c in f.stem for c in args.clips)]
    if not files:
        sys.exit(f"{args.mocap}: no .bvh clips" + (f" matching {args.clips}" if args.clips else "")
                 + " (--mocap DIR or $TFLEARN_MOCAP names the mocap folder)")
    options = replace(mocap.import_options(config.load(ROOT / "configs" / "mocap.yaml").bvh), rate=args.rate,
                      busiest=None if args.whole else args.window, split=args.window if args.whole else None)
    folder = args.out / ("pieces" if args.whole else "windows")
    t0 = time.time()
    report = mocap.import_clips(files, folder, options)
    print(f"imported {len(files)} clips as {len(report['clips'])} motions in {time.time() - t0:.1f} s")
    return report, from_config(report["body"]), folder


def main(argv=None) -> int:
    p = arguments(__doc__.split("\n\n")[0])
    p.add_argument("--import-only", action="store_true", help="print the import table and stop")
    p.add_argument("overrides", nargs="*")
    args = p.parse_args(argv)
    if args.clips:          # key=value after --clips would be read as clip names
        args.overrides += [c for c in args.clips if "=" in c]
        args.clips = [c for c in args.clips if "=" not in c]
    torch.set_num_threads(1)
    with parallel.group("cpu"):          # under torchrun: rank 0 imports, every rank trains
        report = windows = None
        if parallel.rank() == 0:
            report, _, windows = prepare_windows(args)
        report, windows = parallel.broadcast((report, windows))
        if args.import_only:
            if parallel.rank() == 0:
                print(import_table(report))
            return 0
        cfg = config.load(ROOT / "configs" / "mocap.yaml",
                          [f"data={windows}", f"out={args.out / 'run'}",
                           "body=" + json.dumps(report["body"]), *args.overrides])
        t0 = time.time()
        metrics = train.run(cfg, restart=True)
        if parallel.rank() == 0:
            summarise(args, report, metrics, time.time() - t0)
    return 0


def summarise(args, report: dict, metrics: dict, wall: float) -> None:
    """Print the table per window (and with --whole per clip); write OUT/bench.json."""
    rows = metrics["motions"]
    print(f"\n{'window':>44s}  {'from (s)':>8s}  {'rmse (rad)':>10s}  {'tip (cm)':>8s}  reproduced")
    for c in report["clips"]:
        r = rows[c["file"][:-4]]
        print(f"{c['file'][:-4]:>44s}  {c['window_s'][0]:8.2f}  {r['rmse']:10.4f}  "
              f"{100 * r['tip']:8.2f}  {'yes' if r['success'] else 'no'}")
    clips = clip_summary(report, rows) if args.whole else {}
    if clips:
        print(f"\n{'clip':>44s}  pieces  reproduced  {'rmse (rad)':>10s}  {'tip (cm)':>8s}")
    for clip, c in clips.items():
        print(f"{clip:>44s}  {c['pieces']:6d}  {c['reproduced']:10d}  {c['rmse']:10.4f}  "
              f"{100 * c['tip']:8.2f}")
    o = metrics["overall"]
    print(f"M = {o['M']}, overall rmse {o['rmse']:.4f} rad, max tip {100 * o['tip']:.2f} cm, "
          f"all reproduced: {'yes' if o['success'] else 'no'}; training {wall:.0f} s")
    (args.out / "bench.json").write_text(json.dumps(
        {"windows": {c["file"][:-4]: {"from_s": c["window_s"][0], **rows[c["file"][:-4]]}
                     for c in report["clips"]},
         "clips": clips, "overall": o, "wall_s": wall, "overrides": args.overrides}, indent=2, default=float))


if __name__ == "__main__":
    sys.exit(main())
