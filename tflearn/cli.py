"""The ``tflearn`` command line: ``tflearn SUBCOMMAND ...``."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path


def _gestures(args) -> int:
    from . import gestures
    written = gestures.write(args.out, rate=args.rate, plots=not args.no_plots)
    for path in written:
        print(path)
    print(f"wrote {len(gestures.GESTURES)} gestures to {args.out}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="tflearn", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("gestures", help="generate the thesis' gesture library (npz + json + png)")
    p.add_argument("--out", type=Path, default=Path("runs/gestures"), help="output folder")
    p.add_argument("--rate", type=float, default=100.0, help="sampling rate in Hz (default 100)")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG figures")
    p.set_defaults(func=_gestures)
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, FileNotFoundError, KeyError) as err:
        print(f"tflearn {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
