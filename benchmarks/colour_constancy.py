"""Colour constancy: representation floors of the illuminant models, and a small multi-seed study with intervals.

``--floors``: per illuminant family, the best camera-RGB angular error the any-illuminant basis
(:func:`torch_interreflect.spectral.illuminant_basis`) reaches, against the former CIE-daylight ``(M1, M2)`` model
(:mod:`torch_interreflect.training.floors`).

``--study``: ``interreflect train-cc`` with ``--seeds`` training seeds on one generated data set (the held-out
split is the last 20 % of the scenes), then per held-out image and seed the angular errors of every method, and of
the geometry refinement (:func:`torch_interreflect.training.refine_illuminant`) started from the physics-informed
network and from the ∞-bounce FC4 with infinite bounces, and (first seed) two-bounce and direct-only models as
ablations. Differences between methods are paired per image (errors averaged over the seeds first) and given with
percentile-bootstrap 95 % intervals (10,000 resamples of the images). FFCC summaries per method and seed.

Usage::

    .venv/bin/python -m benchmarks.colour_constancy --floors
    .venv/bin/python -m benchmarks.colour_constancy --study                 # small: ~10 min on a 2-core CPU
    .venv/bin/python -m benchmarks.colour_constancy --study --count 2000 --size 64 --epochs 100 --physics-epochs 30

Writes ``benchmarks/results/colour_constancy_floors.md`` / ``colour_constancy_study[...].md`` and ``.json``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from torch_interreflect import spectral
from torch_interreflect.training import (
    BASELINES,
    GeneratedDataset,
    TrainConfig,
    angular_error,
    load_estimator,
    refine_illuminant,
    run_train_cc,
    split_indices,
    summarize,
)
from torch_interreflect.training.floors import daylight_floors, format_floors, representation_floors
from torch_interreflect.training.metrics import format_table

RESULTS = Path(__file__).resolve().parent / "results"


def floors(out: Path) -> str:
    wl = spectral.wavelengths(400, 700, 10, dtype=torch.float64)
    t = time.perf_counter()
    new = representation_floors(wl)
    old = daylight_floors(wl)
    text = ("Representation floors (best camera-RGB angular error, Nikon 5100 (NPL), 400–700 nm / 10 nm; test spectra "
            "off the fitting grid):\n\n" + format_floors(new, "any-illuminant basis, K = 12") + "\n"
            + format_floors(old, "CIE daylight (M1, M2), former box") + f"\n({time.perf_counter() - t:.0f} s)\n")
    (out / "colour_constancy_floors.md").write_text(text)
    return text


def bootstrap(diff: np.ndarray, n: int = 10_000, seed: int = 0) -> tuple[float, float, float]:
    """Mean of ``diff`` and its percentile-bootstrap 95 % interval."""
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, diff.size, (n, diff.size))
    means = diff[idx].mean(1)
    return float(diff.mean()), float(np.percentile(means, 2.5)), float(np.percentile(means, 97.5))


def _net_errors(path: Path, test: GeneratedDataset) -> tuple[np.ndarray, list[torch.Tensor]]:
    est = load_estimator(path)
    errs, preds = [], []
    for k in range(len(test)):
        it = test[k]
        p = est.predict(it["image"])[0]
        preds.append(p)
        errs.append(float(angular_error(p, it["illuminant"])))
    return np.array(errs), preds


def _refined_errors(path: Path, test: GeneratedDataset, starts: list[torch.Tensor], bounces: int | None) -> np.ndarray:
    est = load_estimator(path)
    errs = []
    for k in range(len(test)):
        it = test[k]
        r = refine_illuminant(est, it["image"], it["geometry"], starts[k], bounces=bounces)
        errs.append(float(angular_error(r.rgb.float(), it["illuminant"])))
    return np.array(errs)


def study(args: argparse.Namespace, out: Path) -> str:
    t_all = time.perf_counter()
    errors: dict[str, list[np.ndarray]] = {}
    seconds: dict[str, float] = {}
    test = None
    for seed in range(args.seeds):
        cfg = TrainConfig(data=args.data, out=f"{args.data}/study-seed{seed}", count=args.count, seed=seed,
                          size=(args.size, args.size), epochs=args.epochs, physics_epochs=args.physics_epochs,
                          width=args.width, progress=False, overwrite=True)
        t = time.perf_counter()
        res = run_train_cc(cfg)
        seconds[f"train seed {seed}"] = time.perf_counter() - t
        seconds.update({f"{k} seed {seed}": v for k, v in res["seconds"].items()})
        _, test_idx = split_indices(args.count, cfg.test_fraction)
        test = GeneratedDataset(args.data, None, test_idx, geometry=True)
        if seed == 0:
            for name, fn in BASELINES.items():
                e = [float(angular_error(fn(it["image"][None], it["mask"][None])[0], it["illuminant"]))
                     for it in test]
                errors[name] = [np.array(e)] * args.seeds
        labels = {"fc4_direct": "FC4, direct-only data", "fc4_inf": "FC4, ∞-bounce data",
                  "physics": "physics-informed (network)"}
        starts = {}
        for key, label in labels.items():
            e, starts[key] = _net_errors(cfg.out_dir / f"{key}.pt", test)
            errors.setdefault(label, []).append(e)
        t = time.perf_counter()
        variants = [("physics", None, "physics + geometry refinement, ∞ bounces"),
                    ("fc4_inf", None, "FC4 ∞ + geometry refinement, ∞ bounces")]
        if seed == 0:
            variants += [("physics", 2, "physics + geometry refinement, 2 bounces (seed 0)"),
                         ("physics", 1, "physics + geometry refinement, direct only (seed 0)")]
        for key, b, label in variants:
            errors.setdefault(label, []).append(_refined_errors(cfg.out_dir / f"{key}.pt", test, starts[key], b))
        seconds[f"refine seed {seed}"] = time.perf_counter() - t
    seconds["total"] = time.perf_counter() - t_all
    return _report(args, errors, seconds, len(test) if test is not None else 0, out)


def _report(args: argparse.Namespace, errors: dict[str, list[np.ndarray]], seconds: dict[str, float], n_test: int,
            out: Path) -> str:
    rows: dict[str, dict[str, float]] = {}
    for m, v in errors.items():
        if m in BASELINES:
            rows[m] = summarize(v[0])
        else:
            rows.update({f"{m}, seed {s}": summarize(e) for s, e in enumerate(v)})
    pooled = {m: np.mean(np.stack(v), 0) for m, v in errors.items()}
    pairs = [("physics-informed (network)", "FC4, ∞-bounce data"),
             ("FC4, ∞-bounce data", "FC4, direct-only data"),
             ("physics + geometry refinement, ∞ bounces", "physics-informed (network)"),
             ("physics + geometry refinement, ∞ bounces", "FC4, ∞-bounce data"),
             ("FC4 ∞ + geometry refinement, ∞ bounces", "FC4, ∞-bounce data")]
    e0 = {m: v[0] for m, v in errors.items()}
    pairs0 = [("physics + geometry refinement, ∞ bounces", "physics + geometry refinement, 2 bounces (seed 0)"),
              ("physics + geometry refinement, ∞ bounces", "physics + geometry refinement, direct only (seed 0)")]
    lines = ["| A − B (mean angular error, °) | difference | 95 % interval |", "|---|---:|---:|"]
    for (a, b), src in [(p, pooled) for p in pairs] + [(p, e0) for p in pairs0]:
        if a in src and b in src:
            m, lo, hi = bootstrap(src[a] - src[b])
            tag = " (seed 0)" if src is e0 else " (mean over seeds)"
            lines.append(f"| {a} − {b}{tag} | {m:+.2f} | [{lo:+.2f}, {hi:+.2f}] |")
    header = (f"Study: {args.count} samples at {args.size}×{args.size} (seed-0 data), {n_test} held-out scenes, "
              f"{args.seeds} training seeds, epochs {args.epochs} / physics {args.physics_epochs}, width "
              f"{args.width}; total {seconds['total'] / 60:.1f} min.\n\n")
    text = (header + format_table(rows) + "\n\nPaired differences (negative: A better), percentile bootstrap over the "
            "held-out images:\n\n" + "\n".join(lines) + "\n\nSeconds: "
            + ", ".join(f"{k} {v:.0f}" for k, v in seconds.items()) + "\n")
    stem = f"colour_constancy_study_{args.count}_{args.size}"
    (out / f"{stem}.md").write_text(text)
    (out / f"{stem}.json").write_text(json.dumps({"errors": {m: [e.tolist() for e in v] for m, v in errors.items()},
                                                   "seconds": seconds, "args": vars(args)}, indent=1) + "\n")
    return text


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("--floors", action="store_true")
    p.add_argument("--study", action="store_true")
    p.add_argument("--data", default="out/cc-study")
    p.add_argument("--count", type=int, default=150)
    p.add_argument("--size", type=int, default=32)
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--epochs", type=int, default=30)
    p.add_argument("--physics-epochs", type=int, default=4)
    p.add_argument("--width", type=int, default=8)
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    RESULTS.mkdir(exist_ok=True)
    if args.floors:
        print(floors(RESULTS))
    if args.study:
        print(study(args, RESULTS))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
