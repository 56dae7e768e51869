"""Markdown tables of a `tflearn perturb` run (docs/perturbation.md), and the small copies
of its figures under docs/perturbation/.

    python bench/perturbation_tables.py runs/perturb/gestures [--figures docs/perturbation]

Prints, per motion, the unperturbed tracking RMSE of each controller, the named pushes'
figures, and the sweep summarised per impulse (worst direction, mean over directions).
"""
from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import numpy as np


def _rec(x) -> str:
    return "not recovered" if x is None else f"{x:.2f}"


def tables(doc: dict) -> str:
    out = []
    for name, res in doc["motions"].items():
        out += [f"### {name}", "", "| controller | unperturbed RMSE (rad) | push | max hand dev (cm) | "
                "max joint dev (rad) | recovery (s) | final error (rad) | peak torque (N·m) |",
                "|---|---|---|---|---|---|---|---|"]
        for c, r in res.items():
            for row in r["cases"]:
                if row["case"] == "sweep":
                    continue
                out.append(f"| {c} | {r['rmse']:.2g} | {row['impulse_Ns']:.3g} N·s along "
                           f"{tuple(round(x / row['impulse_Ns'], 2) for x in row['impulse'])} | "
                           f"{100 * row['max_hand_dev']:.2f} | {row['max_joint_dev']:.3f} | "
                           f"{_rec(row['recovery_s'])} | {row['final_joint_error']:.3f} | "
                           f"{row['peak_torque']:.2f} |")
        sweep = {c: [row for row in r["cases"] if row["case"] == "sweep"] for c, r in res.items()}
        if any(sweep.values()):
            imps = sorted({round(row["impulse_Ns"], 6) for rows in sweep.values() for row in rows})
            out += ["", f"Sweep ({len(next(iter(sweep.values()))) // len(imps)} directions per "
                    "impulse): largest hand deviation in cm, worst direction / mean; recovered "
                    "pushes out of all; peak torque N·m (worst)", "",
                    "| controller | " + " | ".join(f"{j:g} N·s" for j in imps) + " | recovered | "
                    "mean recovery (s) |", "|---|" + "---|" * (len(imps) + 2)]
            for c, rows in sweep.items():
                cells = []
                for j in imps:
                    rs = [row for row in rows if round(row["impulse_Ns"], 6) == j]
                    d = [100 * row["max_hand_dev"] for row in rs]
                    peak = max(row["peak_torque"] for row in rs)
                    cells.append(f"{max(d):.1f} / {np.mean(d):.1f}; {peak:.1f}")
                rec = [row["recovery_s"] for row in rows]
                ok = [x for x in rec if x is not None]
                out.append(f"| {c} | " + " | ".join(cells) + f" | {len(ok)}/{len(rec)} | "
                           + (f"{np.mean(ok):.2f} |" if ok else "– |"))
        out.append("")
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--figures", type=Path, default=None, help="copy the PNG figures here")
    args = ap.parse_args()
    doc = json.loads((args.run / "results.json").read_text())
    print(tables(doc))
    if args.figures:
        args.figures.mkdir(parents=True, exist_ok=True)
        for png in sorted((args.run / "figures").glob("*.png")):
            shutil.copy(png, args.figures / png.name)


if __name__ == "__main__":
    main()
