"""The ``interreflect`` command."""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence

from ..training.argtypes import positive_float, positive_int
from ..training.commands import ArgumentParser, add_generate_parser, add_train_parser, run_command
from .predict import add_predict_parser

__all__ = ["main"]


def _demo(args: argparse.Namespace) -> int:
    from .demo import DemoConfig, run_demo

    cfg = DemoConfig(angles=tuple(args.angles), divisions=args.divisions)
    t = time.perf_counter()
    res = run_demo(args.out, cfg, progress=not args.no_progress)
    elapsed = time.perf_counter() - t
    for angle, tm in res["timings"].items():
        if isinstance(tm, dict):
            print(f"V-groove {angle}°: {tm['facets']} facets, {tm['pairs']} facet pairs; "
                  f"form factors {tm['kernel_s']:.2f} s, 4 solves × {len(cfg.patches)} patches × "
                  f"{len(cfg.illuminants)} illuminants {tm['solve_s']:.2f} s")
    print("\nRelative RMS difference to infinite bounces, worst channel (%): hinge column / all facets")
    first_ill = next(iter(cfg.illuminants))
    header = f"{'patch':8s}" + "".join(f" | {a + '°, ' + b + ' bounces':>22s}" for a in res["table"] for b in "234")
    print(header)
    for p in cfg.patches:
        row = f"{p:8s}"
        for a in res["table"]:
            for b in "234":
                v = res["table"][a][first_ill][p][b]
                row += f" | {max(v['hinge_column_%']):9.2f} / {max(v['overall_%']):8.2f}"
        print(row)
    print(f"(illuminant {first_ill}; every illuminant in table9.md)\n")
    print("Wrote:")
    for path in res["written"]:
        print(f"  {path}")
    print(f"Done in {elapsed:.1f} s.")
    return 0


def _angle(text: str) -> float:
    v = positive_float(text)
    if v >= 180.0:
        raise argparse.ArgumentTypeError(f"expected a groove angle in (0, 180) degrees; got {text!r}")
    return v


def build_parser() -> ArgumentParser:
    """The parser of ``interreflect`` (sub-commands ``demo``, ``generate``, ``train-cc``, ``predict``)."""
    parser = ArgumentParser(prog="interreflect", description=__doc__)
    parser.add_argument("--debug", action="store_true", help="show the full traceback of an error")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=ArgumentParser)
    p = sub.add_parser("demo", help="the paper's V-groove experiment: n-bounce vs infinite-bounce camera RGB")
    p.add_argument("--out", default="out/demo", help="output folder (default: out/demo)")
    p.add_argument("--angles", type=_angle, nargs="+", default=[45.0, 60.0], help="groove angles in degrees")
    p.add_argument("--divisions", type=positive_int, default=10,
                   help="facets per plate edge (default 10, as the paper)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                   help="show the full traceback of an error")
    p.set_defaults(func=_demo)
    add_generate_parser(sub)
    add_train_parser(sub)
    add_predict_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``interreflect`` console script.

    Returns:
        The exit status: 0, 2 for a usage error (one line on stderr), 1 for another error, 130 for Ctrl-C.
    """
    return run_command(build_parser(), argv)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
