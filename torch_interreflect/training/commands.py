"""The ``generate`` and ``train-cc`` sub-commands of ``interreflect``, and how every command fails.

:func:`run_command` runs a parsed command the same way for ``interreflect`` and the stand-alone entry points:

- a usage error (a bad option value, an unknown camera, a folder of another configuration, results that would be
  overwritten) prints one line ``interreflect: error: …`` to stderr and exits with status 2;
- any other error prints one line naming its type and exits with status 1;
- Ctrl-C (SIGINT) prints ``interreflect: interrupted`` and exits with status 130 (128 + SIGINT);
- ``--debug`` shows the full traceback instead.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from typing import Any, NoReturn

from . import argtypes
from .config import SHADINGS, GeneratorConfig
from .generator import generate
from .random_scenes import ILLUMINANT_KINDS, SCENE_KINDS
from .train import TrainConfig, run_train_cc

__all__ = [
    "ArgumentParser",
    "add_generate_parser",
    "add_train_parser",
    "main_generate",
    "main_train",
    "run_command",
]

#: Errors that mean the command was asked for something it cannot do (exit status 2, like argparse's).
USAGE_ERRORS: tuple[type[BaseException], ...] = (ValueError, FileExistsError, FileNotFoundError)


class ArgumentParser(argparse.ArgumentParser):
    """An :class:`argparse.ArgumentParser` whose errors are one line (``prog: error: message``), exit status 2."""

    def error(self, message: str) -> NoReturn:
        """Print ``prog: error: message (see prog --help)`` and exit with status 2."""
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _debug_parent() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                   help="show the full traceback of an error")
    return p


def add_generate_parser(sub: Any) -> argparse.ArgumentParser:
    """Add the ``generate`` sub-command to an ``argparse`` sub-parsers object (``parser.add_subparsers()``)."""
    from . import generator

    p = sub.add_parser("generate", help="synthetic colour-constancy data: random concave scenes, exact interreflection",
                       description=(generator.__doc__ or "").split("\n\n")[0], parents=[_debug_parent()])
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--count", type=argtypes.nonnegative_int, required=True,
                   help="number of samples (indices 0 … count-1); a larger count grows an existing folder")
    p.add_argument("--seed", type=argtypes.nonnegative_int, default=0, help="base seed (default 0)")
    p.add_argument("--shard", type=argtypes.shard, default=(0, 1), help="i/n: render indices i, i+n, … (default 0/1)")
    p.add_argument("--scenes", nargs="+", default=list(SCENE_KINDS), choices=SCENE_KINDS, help="scene kinds")
    p.add_argument("--illuminants", nargs="+", default=list(ILLUMINANT_KINDS), choices=ILLUMINANT_KINDS,
                   help="illuminant families")
    p.add_argument("--camera", default="Nikon 5100 (NPL)", help="camera sensitivities (default Nikon 5100 (NPL))")
    p.add_argument("--size", type=argtypes.image_size, default=(64, 64), help="image size HxW (default 64x64)")
    p.add_argument("--bounces", type=argtypes.bounce_count, nargs="+", default=[None, 1, 2],
                   help="variants: inf (always written) and n-bounce models, e.g. 1 (direct only) 2 (default: inf 1 2)")
    p.add_argument("--supersample", type=argtypes.positive_int, default=GeneratorConfig.supersample,
                   help=f"sub-pixel rays per pixel side (default {GeneratorConfig.supersample})")
    p.add_argument("--edge-supersample", type=argtypes.positive_int, default=GeneratorConfig.edge_supersample,
                   help="rays per pixel side in pixels where those rays see an edge (gather shading; default "
                        f"{GeneratorConfig.edge_supersample}; 1 or at most --supersample: uniform)")
    p.add_argument("--shading", choices=SHADINGS, default="gather",
                   help="gather: per-pixel final gather, soft shadows (default); flat: one colour per facet, faster")
    p.add_argument("--no-split-contacts", action="store_true",
                   help="do not split facets where another facet stands on them (the behaviour of 0.1.0)")
    p.add_argument("--visibility-samples", type=argtypes.positive_int, default=2,
                   help="with gather: visibility rays per side of a target facet that may be blocked (default 2)")
    p.add_argument("--gather-stride", type=argtypes.positive_int, default=1,
                   help="with gather: gather every n pixels per side and interpolate (faster, less exact; default 1)")
    p.add_argument("--no-geometry", action="store_true", help="do not write the _geometry.npz files")
    p.add_argument("--workers", type=argtypes.workers, default="auto",
                   help="processes rendering at once, or auto (default): one per 32 samples left to render, up to "
                        "the usable cores; the same bytes whatever the number")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.set_defaults(func=_run_generate)
    return p


def _run_generate(args: argparse.Namespace) -> int:
    config = GeneratorConfig(
        count=args.count, seed=args.seed, scenes=tuple(args.scenes), illuminants=tuple(args.illuminants),
        camera=args.camera, size=args.size, bounces=tuple(dict.fromkeys([None, *args.bounces])),
        supersample=args.supersample, geometry=not args.no_geometry, shading=args.shading,
        split_contacts=not args.no_split_contacts, visibility_samples=args.visibility_samples,
        gather_stride=args.gather_stride, edge_supersample=args.edge_supersample,
    )
    res = generate(args.out, config, shard=args.shard, progress=not args.no_progress, workers=args.workers)
    removed = f", removed {len(res.removed)} stale temporary files" if res.removed else ""
    procs = f" on {res.workers} processes" if res.workers > 1 else ""
    print(f"shard {args.shard[0]}/{args.shard[1]}: wrote {len(res.written)} samples, skipped {len(res.skipped)} "
          f"complete ones{removed}, in {res.seconds:.1f} s{procs} ({res.samples_per_second:.2f} samples/s) "
          f"-> {args.out}")
    return 0


def add_train_parser(sub: Any) -> argparse.ArgumentParser:
    """Add the ``train-cc`` sub-command to an ``argparse`` sub-parsers object."""
    from . import train

    d = TrainConfig()
    p = sub.add_parser("train-cc", help="colour constancy on generated data: baselines, CNNs, physics-informed model",
                       description=(train.__doc__ or "").split("\n\n")[0], parents=[_debug_parent()])
    p.add_argument("--data", default=d.data,
                   help=f"generated data folder, created or grown if needed (default {d.data})")
    p.add_argument("--out", default=None, help="results and weights (default <data>/train-cc)")
    p.add_argument("--overwrite", action="store_true", help="replace results and weights of an earlier run in --out")
    p.add_argument("--count", type=argtypes.positive_int, default=d.count, help=f"samples (default {d.count})")
    p.add_argument("--seed", type=argtypes.nonnegative_int, default=d.seed,
                   help="seed of new data and of the training (default 0)")
    p.add_argument("--size", type=argtypes.image_size, default=None,
                   help="image size HxW (default: the data's; 64x64 for new data); must match existing data")
    p.add_argument("--test-fraction", type=argtypes.fraction, default=d.test_fraction,
                   help="held-out fraction (default 0.2)")
    p.add_argument("--epochs", type=argtypes.nonnegative_int, default=d.epochs,
                   help=f"epochs of each CNN (default {d.epochs})")
    p.add_argument("--physics-epochs", type=argtypes.nonnegative_int, default=d.physics_epochs,
                   help=f"epochs of the physics-informed model, 0 to skip (default {d.physics_epochs})")
    p.add_argument("--batch-size", type=argtypes.positive_int, default=d.batch_size,
                   help=f"per process (default {d.batch_size})")
    p.add_argument("--lr", type=argtypes.positive_float, default=d.lr, help=f"Adam learning rate (default {d.lr})")
    p.add_argument("--width", type=argtypes.positive_int, default=d.width, help=f"network width (default {d.width})")
    p.add_argument("--reconstruction-weight", type=float, default=d.reconstruction_weight,
                   help=f"weight of the re-rendering loss (default {d.reconstruction_weight})")
    p.add_argument("--threads", type=argtypes.nonnegative_int, default=d.threads,
                   help="torch threads per process (default 1; 0 = torch's choice)")
    p.add_argument("--no-progress", action="store_true", help="hide progress bars")
    p.set_defaults(func=_run_train)
    return p


def _run_train(args: argparse.Namespace) -> int:
    cfg = TrainConfig(
        data=args.data, out=args.out, count=args.count, seed=args.seed, size=args.size,
        test_fraction=args.test_fraction, epochs=args.epochs, physics_epochs=args.physics_epochs,
        batch_size=args.batch_size, lr=args.lr, width=args.width, reconstruction_weight=args.reconstruction_weight,
        threads=args.threads or None, progress=not args.no_progress, overwrite=args.overwrite,
    )
    res = run_train_cc(cfg)
    if res["table"]:
        print(res["table"])
        print("\nSeconds: " + ", ".join(f"{k} {v:.0f}" for k, v in res["seconds"].items()))
        print(f"Wrote {cfg.out_dir}/results.md, results.json and the weights.")
    return 0


def run_command(parser: argparse.ArgumentParser, argv: Sequence[str] | None) -> int:
    """Parse ``argv`` and run the chosen command's ``func``; turn failures into one line and an exit status.

    Args:
        parser: A parser whose sub-commands set ``func`` (``args.func(args) → int``).
        argv: The arguments (default ``sys.argv[1:]``).

    Returns:
        The exit status: the command's, 2 for a usage error, 1 for another error, 130 for Ctrl-C.
    """
    args = parser.parse_args(argv)
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        return int(func(args))
    except KeyboardInterrupt:
        if getattr(args, "debug", False):
            raise
        print(f"\n{parser.prog}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:
        if getattr(args, "debug", False):
            raise
        usage = isinstance(exc, USAGE_ERRORS)
        kind = "error" if usage else f"error ({type(exc).__name__})"
        message = " ".join(str(exc).split()) or type(exc).__name__
        print(f"{parser.prog}: {kind}: {message} (run with --debug for the traceback)", file=sys.stderr)
        return 2 if usage else 1


def _main(name: str, add: Callable[[Any], argparse.ArgumentParser], argv: Sequence[str] | None) -> int:
    parser = ArgumentParser(prog="interreflect")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=ArgumentParser)
    add(sub)
    return run_command(parser, [name, *(argv if argv is not None else sys.argv[1:])])


def main_generate(argv: Sequence[str] | None = None) -> int:
    """``interreflect generate`` as a stand-alone entry point."""
    return _main("generate", add_generate_parser, argv)


def main_train(argv: Sequence[str] | None = None) -> int:
    """``interreflect train-cc`` as a stand-alone entry point (also ``torchrun -m torch_interreflect.cli train-cc``)."""
    return _main("train-cc", add_train_parser, argv)
