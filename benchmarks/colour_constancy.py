"""Colour constancy: representation floors of the illuminant models, and a multi-seed study with intervals.

``--floors``: per illuminant family, the best camera-RGB angular error the any-illuminant basis
(:func:`torch_interreflect.spectral.illuminant_basis`) reaches, against the former CIE-daylight ``(M1, M2)`` model
(:mod:`torch_interreflect.training.floors`).

``--study``: ``interreflect train-cc`` with ``--seeds`` training seeds on one generated data set (generated first by
``--workers`` processes at once, ``generate``'s workers; the held-out split is the last 20 % of the scenes, of which
the first ``--max-test`` are scored), then per test image and seed the angular errors of every method:

- without geometry: Grey-World, White-Patch, Grey-Edge, the FC4-style CNN trained on direct-only, two-bounce and
  ∞-bounce images, the physics-informed network;
- with geometry: the refinement by re-rendering (:func:`torch_interreflect.training.refine_illuminant`, infinite
  bounces) started from the physics-informed network and from the ∞-bounce FC4; for the first seed also two-bounce
  and direct-only re-rendering (ablations) and the refinement started from the true illuminant (what the model
  mismatch alone costs).

Two test sets: the generator's held-out scenes, and (``--pathtraced N``, default 200, when Mitsuba 3 is installed)
``N`` images path-traced by Mitsuba 3 with their geometry files (:mod:`benchmarks.cc_pathtraced`: sun + sky, grooves,
folds, rooms with blocks; half the illuminants and reflectances from outside the training families).
Differences between methods are paired per image (errors averaged over the seeds first) and given with
percentile-bootstrap 95 % intervals (10,000 resamples of the images). FFCC summaries per method and seed.
Refinements run in ``--workers`` processes of one torch thread each. The report also gives the median errors per scene
kind; ``--report JSON`` rewrites a report from its ``.json`` (same tables, no training).

Usage::

    .venv/bin/python -m benchmarks.colour_constancy --floors
    .venv/bin/python -m benchmarks.colour_constancy --study        # default: see README for its size and time
    .venv/bin/python -m benchmarks.colour_constancy --study --count 20000 --size 64 --epochs 100 --physics-epochs 30
    python -m benchmarks.colour_constancy --report benchmarks/results/colour_constancy_study_5000_32_pt200.json

Writes ``colour_constancy_floors.md`` / ``colour_constancy_study_{count}_{size}[_pt{N}].md`` and ``.json`` into
``--out`` (default ``benchmarks/results``).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import torch

from benchmarks._common.mitsuba import available as mitsuba_available
from benchmarks.cc_pathtraced import OUTSIDE_FAMILIES, SPP, render_test_set
from torch_interreflect import spectral
from torch_interreflect.training import (
    BASELINES,
    GeneratedDataset,
    GeneratorConfig,
    TrainConfig,
    angular_error,
    generate,
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


def _refine_images(path: str, root: str, indices: list[int], starts: list[list[float]], bounces: int | None
                   ) -> list[float]:
    """Angular errors of :func:`refine_illuminant` on samples ``indices`` of ``root`` (one worker's share)."""
    torch.set_num_threads(1)
    est = load_estimator(path)
    test = GeneratedDataset(root, None, indices, geometry=True)
    out = []
    for it, start in zip(test, starts, strict=True):
        r = refine_illuminant(est, it["image"], it["geometry"], torch.tensor(start), bounces=bounces)
        out.append(float(angular_error(r.rgb.float(), it["illuminant"])))
    return out


def _refined_errors(path: Path, test: GeneratedDataset, starts: list[torch.Tensor], bounces: int | None,
                    pool: tuple[ProcessPoolExecutor, int] | None) -> np.ndarray:
    """Errors of the geometry refinement from ``starts`` on every image of ``test``, split over the ``(executor,
    workers)`` processes (one torch thread each; ``None``: here)."""
    n = len(test)
    parts = 1 if pool is None else pool[1]
    chunks = [c for c in (list(range(k, n, parts)) for k in range(parts)) if c]
    jobs = [(str(path), str(test.root), [test.indices[i] for i in c], [starts[i].tolist() for i in c], bounces)
            for c in chunks]
    if pool is None:
        results = [_refine_images(*j) for j in jobs]
    else:
        results = [f.result() for f in [pool[0].submit(_refine_images, *j) for j in jobs]]
    errs = np.empty(n)
    for c, r in zip(chunks, results, strict=True):
        errs[c] = r
    return errs


def _score(test: GeneratedDataset, out_dir: Path, seed: int, errors: dict[str, list[np.ndarray]],
           pool: tuple[ProcessPoolExecutor, int] | None) -> None:
    """Append seed ``seed``'s errors of every method on ``test`` to ``errors`` (the baselines once, at seed 0)."""
    if seed == 0:
        for name, fn in BASELINES.items():
            e = [float(angular_error(fn(it["image"][None], it["mask"][None])[0], it["illuminant"])) for it in test]
            errors[name] = [np.array(e)]
    labels = {"fc4_direct": "FC4, direct-only data", "fc4_b2": "FC4, 2-bounce data", "fc4_inf": "FC4, ∞-bounce data",
              "physics": "physics-informed (network)"}
    starts = {}
    for key, label in labels.items():
        if not (out_dir / f"{key}.pt").is_file():  # e.g. data without direct-only or 2-bounce images
            continue
        e, starts[key] = _net_errors(out_dir / f"{key}.pt", test)
        errors.setdefault(label, []).append(e)
    variants = [("physics", None, "physics + geometry refinement, ∞ bounces"),
                ("fc4_inf", None, "FC4 ∞ + geometry refinement, ∞ bounces")]
    if seed == 0:  # ablations, and the model's own floor: the refinement started at the answer
        starts["truth"] = [it["illuminant"] for it in test]
        variants += [("physics", 2, "physics + geometry refinement, 2 bounces (seed 0)"),
                     ("physics", 1, "physics + geometry refinement, direct only (seed 0)"),
                     ("truth", None, "geometry refinement from the true illuminant (seed 0)")]
    for key, b, label in variants:
        path = out_dir / f"{'physics' if key == 'truth' else key}.pt"
        errors.setdefault(label, []).append(_refined_errors(path, test, starts[key], b, pool))


def _generate(args: argparse.Namespace) -> None:
    """The seed-0 data of the study, rendered by ``args.workers`` processes at once (``generate``'s workers)."""
    gen = GeneratorConfig(count=args.count, seed=0, size=(args.size, args.size))
    generate(args.data, gen, progress=False, workers=max(1, args.workers))


def _pathtraced_root(args: argparse.Namespace) -> Path:
    return Path(args.data).parent / f"cc-pathtraced-{args.size}-{SPP}spp"


def _pathtraced_set(args: argparse.Namespace) -> GeneratedDataset:
    """The first ``args.pathtraced`` images of the path-traced set (its folder may hold more)."""
    root = _pathtraced_root(args)
    first = json.loads((root / "dataset.json").read_text())["indices"][: args.pathtraced]
    return GeneratedDataset(root, None, first, geometry=True)


def _held_out(args: argparse.Namespace, test_fraction: float) -> GeneratedDataset:
    """The first ``args.max_test`` held-out scenes of the study's data."""
    _, test_idx = split_indices(args.count, test_fraction)
    return GeneratedDataset(args.data, None, test_idx[: args.max_test], geometry=True)


def study(args: argparse.Namespace, out: Path) -> str:
    t_all = time.perf_counter()
    errors: dict[str, dict[str, list[np.ndarray]]] = {}
    seconds: dict[str, float] = {}
    sets: dict[str, GeneratedDataset] = {}
    spawn = multiprocessing.get_context("spawn")
    ex = ProcessPoolExecutor(args.workers, mp_context=spawn) if args.workers > 1 else None
    pool = None if ex is None else (ex, args.workers)
    if args.pathtraced:
        t = time.perf_counter()
        render_test_set(_pathtraced_root(args), args.pathtraced, args.size, progress=False)
        sets["path-traced (Mitsuba)"] = _pathtraced_set(args)
        seconds["path-traced set"] = time.perf_counter() - t
    try:
        t = time.perf_counter()
        _generate(args)
        seconds["data"] = time.perf_counter() - t
        for seed in range(args.seeds):
            cfg = TrainConfig(data=args.data, out=f"{args.data}/study-seed{seed}", count=args.count, seed=seed,
                              size=(args.size, args.size), epochs=args.epochs, physics_epochs=args.physics_epochs,
                              width=args.width, progress=False, overwrite=True)
            t = time.perf_counter()
            res = run_train_cc(cfg)
            seconds[f"train seed {seed}"] = time.perf_counter() - t
            seconds.update({f"{k} seed {seed}": v for k, v in res["seconds"].items() if k != "data"})
            sets = {"held-out (generator)": _held_out(args, cfg.test_fraction), **sets}
            for name, test in sets.items():
                t = time.perf_counter()
                _score(test, cfg.out_dir, seed, errors.setdefault(name, {}), pool)
                seconds[f"score {name} seed {seed}"] = time.perf_counter() - t
    finally:
        if ex is not None:
            ex.shutdown()
    seconds["total"] = time.perf_counter() - t_all
    kinds = {name: scene_kinds(test) for name, test in sets.items()}
    groups = {name: outside_groups(test) for name, test in sets.items()}
    return _report(args, errors, seconds, {k: len(v) for k, v in sets.items()}, out, kinds, groups)


def report(path: Path, out: Path) -> str:
    """Rewrite a study's ``.md`` (and ``.json``) from its ``.json`` (e.g. after the report gained a table): the same
    errors and seconds; the scene kinds and training-family groups read from the data folders when the file has none
    (without those folders, a file with scene kinds is rewritten without the groups)."""
    saved = json.loads(path.read_text())
    args = argparse.Namespace(**saved["args"])
    errors = {n: {m: [np.array(x) for x in v] for m, v in e.items()} for n, e in saved["errors"].items()}
    kinds, groups = saved.get("scene_kinds") or {}, saved.get("outside_groups") or {}
    for name in errors:
        if name in kinds and name in groups:
            continue
        try:
            test = (_held_out(args, TrainConfig().test_fraction) if name.startswith("held-out")
                    else _pathtraced_set(args))
            if name not in kinds:
                kinds[name] = scene_kinds(test)
            if name not in groups:
                groups[name] = outside_groups(test)
        except OSError:  # the data folders are gone: the training-family table needs them, the rest does not
            if name not in kinds:
                raise
    sizes = {name: len(kinds[name]) for name in errors}
    return _report(args, errors, saved["seconds"], sizes, out, kinds, groups)


def _tables(errors: dict[str, list[np.ndarray]]) -> str:
    """The per-method table and the paired differences of one test set."""
    rows: dict[str, dict[str, float]] = {}
    for m, v in errors.items():
        if m in BASELINES:
            rows[m] = summarize(v[0])
        else:
            rows.update({f"{m}, seed {s}": summarize(e) for s, e in enumerate(v)})
    pooled = {m: np.mean(np.stack(v), 0) for m, v in errors.items()}
    pairs = [("physics-informed (network)", "FC4, ∞-bounce data"),
             ("FC4, ∞-bounce data", "FC4, direct-only data"),
             ("FC4, ∞-bounce data", "FC4, 2-bounce data"),
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
    return (format_table(rows) + "\n\nPaired differences (negative: A better), percentile bootstrap over the "
            "images:\n\n" + "\n".join(lines) + "\n")


#: Methods of the per-scene-kind table (their per-image errors averaged over the seeds first).
KIND_METHODS = ("FC4, ∞-bounce data", "physics-informed (network)", "physics + geometry refinement, ∞ bounces",
                "FC4 ∞ + geometry refinement, ∞ bounces", "geometry refinement from the true illuminant (seed 0)")


def scene_kinds(test: GeneratedDataset) -> list[str]:
    """The scene kind (``"v_groove"``, ``"cornell"``, …) of every image of ``test``, from its sidecar."""
    return [json.loads((test.root / f"{i:06d}.json").read_text())["scene"]["kind"] for i in test.indices]


def outside_groups(test: GeneratedDataset) -> list[list[str]]:
    """Per image of ``test``, from its sidecar: whether its illuminant and its reflectances come from inside the
    training families (``"illuminant inside"`` / ``"illuminant outside"``, ``"reflectances all inside"`` / ``"a
    reflectance outside"``; :mod:`benchmarks.cc_pathtraced` draws the outside ones)."""
    out = []
    for i in test.indices:
        meta = json.loads((test.root / f"{i:06d}.json").read_text())
        kind = meta["illuminant"].get("kind", "")
        ill = kind.endswith("(outside)") or kind in OUTSIDE_FAMILIES
        refl = any("(outside)" in m.get("source", "") for m in meta["materials"])
        out.append(["illuminant " + ("outside" if ill else "inside"),
                    "a reflectance outside" if refl else "reflectances all inside"])
    return out


def _by_kind(errors: dict[str, list[np.ndarray]], kinds: list[str] | list[list[str]],
             what: str = "scene kind") -> str:
    """Median errors per scene kind, or per group (an image may be in several), of :data:`KIND_METHODS` (images
    averaged over the seeds)."""
    methods = [m for m in KIND_METHODS if m in errors]
    lines = [f"| {what} | images | " + " | ".join(methods) + " |", "|---|---:|" + "---:|" * len(methods)]
    groups = [k if isinstance(k, list) else [k] for k in kinds]
    for k in sorted({g for gs in groups for g in gs}):
        sel = np.array([k in gs for gs in groups])
        meds = [float(np.median(np.mean(np.stack(errors[m]), 0)[sel])) for m in methods]
        lines.append(f"| {k} | {int(sel.sum())} | " + " | ".join(f"{v:.2f}" for v in meds) + " |")
    return (f"\nMedian errors (°) per {what}, each image's error averaged over the seeds first:\n\n"
            + "\n".join(lines) + "\n")


def _report(args: argparse.Namespace, errors: dict[str, dict[str, list[np.ndarray]]], seconds: dict[str, float],
            sizes: dict[str, int], out: Path, kinds: dict[str, list[str]] | None = None,
            groups: dict[str, list[list[str]]] | None = None) -> str:
    header = (f"Study: {args.count} samples at {args.size}×{args.size} (seed-0 data), {args.seeds} training seeds, "
              f"epochs {args.epochs} / physics {args.physics_epochs}, width {args.width}; total "
              f"{seconds['total'] / 60:.1f} min.\n")
    kinds, groups = kinds or {}, groups or {}
    mixed = {n for n, g in groups.items() if len({tuple(x) for x in g}) > 1}  # the held-out set is all inside
    body = "".join(f"\n## Test set: {name}, {sizes[name]} images\n\n" + _tables(e)
                   + (_by_kind(e, kinds[name]) if name in kinds else "")
                   + (_by_kind(e, groups[name], "training family") if name in mixed else "")
                   for name, e in errors.items())
    text = header + body + "\nSeconds: " + ", ".join(f"{k} {v:.0f}" for k, v in seconds.items()) + "\n"
    stem = f"colour_constancy_study_{args.count}_{args.size}" + (f"_pt{args.pathtraced}" if args.pathtraced else "")
    (out / f"{stem}.md").write_text(text)
    dump = {"errors": {n: {m: [x.tolist() for x in v] for m, v in e.items()} for n, e in errors.items()},
            "seconds": seconds, "args": vars(args), "scene_kinds": kinds, "outside_groups": groups}
    (out / f"{stem}.json").write_text(json.dumps(dump, indent=1) + "\n")
    return text


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("--floors", action="store_true")
    p.add_argument("--study", action="store_true")
    p.add_argument("--data", default="out/cc-study")
    p.add_argument("--count", type=int, default=5000)
    p.add_argument("--size", type=int, default=32)
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--epochs", type=int, default=30)
    p.add_argument("--physics-epochs", type=int, default=4)
    p.add_argument("--width", type=int, default=8)
    p.add_argument("--workers", type=int, default=2, help="processes for the data and the refinements")
    p.add_argument("--max-test", type=int, default=200, help="held-out images scored (the first ones)")
    p.add_argument("--pathtraced", type=int, default=200, metavar="N",
                   help="also score on N Mitsuba path-traced images with geometry (benchmarks.cc_pathtraced; "
                        "0: not; skipped when Mitsuba is missing)")
    p.add_argument("--out", default=str(RESULTS), help="folder of the result files (default: benchmarks/results; "
                   "a smoke run's results belong elsewhere)")
    p.add_argument("--report", metavar="JSON", help="rewrite a study's report from its .json (no training)")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.study and args.pathtraced and not mitsuba_available("llvm_ad_spectral"):
        print("Mitsuba 3 (llvm_ad_spectral) is not available (`make bench-install`): no path-traced test set")
        args.pathtraced = 0
    if args.floors:
        print(floors(out))
    if args.study:
        print(study(args, out))
    if args.report:
        print(report(Path(args.report), out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
