"""Visibility on an occluded scene: how much of the error is the visibility sampling's, and at what cost.

The Cornell box under a uniform sky (the cached Mitsuba references ``cornell_sky_r2`` / ``cornell_sky_r9``, 16
user facets), refined uniformly (``Scene.subdivide(k)``), and the open room (``room_sky_r2`` / ``room_sky_r9``, 114
facets, ``k = 1, 2``). For each ``k`` and visibility setting — the fixed
``n × n`` grid (``visibility_samples=n``), the adaptive split of shadow-boundary cells (``visibility_tol``), the
default (``n = 3`` with fewer samples for small-looking targets, ``visibility_angle=0.3``), and ``n = 30`` on every
target (100× the rays of ``n = 3``) as the visibility reference — it reports the kernel's wall
time and rays, the total error of the area-averaged irradiance against Mitsuba (relative RMS over the user facets),
and the *visibility part*: the same error measure between the setting and the ``n = 30`` reference. The *split*
rows solve the scene split at its contact lines first (:func:`~torch_interreflect.geometry.split_at_contacts`),
also at ``k = 8``. The default and the reference are also solved with the sky's two estimates of its open part
weighed per facet (:func:`~torch_interreflect.solver.solve_sky`), the *weighed sky* rows.

Usage: ``python -m benchmarks.visibility [--quick]`` → ``benchmarks/results/visibility[_quick].md``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

import torch_interreflect as ti
from torch_interreflect.geometry import area_average
from torch_interreflect.sky_parts import sky_open_parts
from torch_interreflect.solver import solve_sky

from ._common import mitsuba as mr
from ._common.ours import split_and_subdivide
from ._common.report import rel_errors

RESULTS = Path(__file__).resolve().parent / "results"
#: (visibility_samples, visibility_tol, visibility_angle, visibility_jitter); the first is the default, the second
#: the default before jittered samples (cell midpoints), the last the reference
SETTINGS = [(3, None, 0.3, True), (3, None, 0.3, False), (3, None, None, True), (3, 1e-3, None, True),
            (10, None, None, True), (30, None, None, True)]


def run(name: str, ks: list[int], split_only: tuple[int, ...] = ()) -> list[dict]:
    """One row per (k, setting) for the reference ``name``, and the split scene alone at ``split_only``."""
    ref = mr.load_reference(name)
    spec = ref["settings"]
    scene = mr.build_scene(spec)
    r, radiance = float(spec["reflectance"]), float(spec["light"]["radiance"])
    e_ref = np.asarray(ref["irradiance"], np.float64)
    rows = []
    for k in ks:
        fine, parent = scene.subdivide(k)
        got, weighed = {}, {}
        refl = torch.full((fine.num_facets,), r, dtype=torch.float64)
        L = torch.full((1,), radiance, dtype=torch.float64)
        for n, tol, angle, jitter in SETTINGS:
            t0 = time.perf_counter()
            K = ti.form_factors(fine, visibility_samples=n, visibility_tol=tol, visibility_angle=angle,
                                visibility_jitter=jitter, progress=False)
            seconds = time.perf_counter() - t0
            e = ti.solve(K, refl, ti.lights.sky(fine, K, L))
            ec = scene.average_to_parent(e.reshape(fine.num_facets, -1), parent, fine).numpy().reshape(-1)
            got[(n, tol, angle, jitter)] = (seconds, int(K.info.get("rays", 0)), ec)
            if (n, tol, angle, jitter) in (SETTINGS[0], SETTINGS[-1]):  # the default and the reference, weighed
                e = solve_sky(K, refl, *sky_open_parts(fine, K), L)
                ec = scene.average_to_parent(e.reshape(fine.num_facets, -1), parent, fine).numpy().reshape(-1)
                weighed[(n, tol, angle, jitter)] = (seconds, int(K.info.get("rays", 0)), ec)
        for table, flag in ((got, False), (weighed, True)):
            best = table[SETTINGS[-1]][2]
            for (n, tol, angle, jitter), (seconds, rays, ec) in table.items():
                rows.append({
                    "scene": name, "k": k, "facets": fine.num_facets, "n": n, "tol": tol, "angle": angle,
                    "jitter": jitter, "weighed": flag,
                    "seconds": seconds,
                    "rays": rays, "total": rel_errors(ec, e_ref)[0],
                    "visibility": float(np.sqrt(np.mean(((ec - best) / e_ref) ** 2))),
                    "bias": float(np.mean((ec - e_ref) / e_ref)), "contacts": False,
                })
                print(rows[-1], flush=True)
        rows.append(_split_row(name, scene, k, r, radiance, e_ref))
    rows += [_split_row(name, scene, k, r, radiance, e_ref) for k in split_only]
    return rows


def _split_row(name: str, scene, k: int, r: float, radiance: float, e_ref: np.ndarray) -> dict:
    """The default kernel (n = 3, angle 0.3) on the scene split at its contact lines first, then ``subdivide(k)``."""
    fine, user = split_and_subdivide(scene, k)
    t0 = time.perf_counter()
    K = ti.form_factors(fine, progress=False)
    seconds = time.perf_counter() - t0
    e0 = ti.lights.sky(fine, K, torch.full((1,), radiance, dtype=torch.float64))
    e = ti.solve(K, torch.full((fine.num_facets,), r, dtype=torch.float64), e0)
    ec = area_average(e.reshape(fine.num_facets, -1), user, fine.areas, scene.num_facets)
    ec = ec.numpy().reshape(-1)
    row = {"scene": name, "k": k, "facets": fine.num_facets, "n": 3, "tol": None, "angle": 0.3, "jitter": True,
           "seconds": seconds,
           "rays": int(K.info.get("rays", 0)), "total": rel_errors(ec, e_ref)[0],
           "visibility": float("nan"), "bias": float(np.mean((ec - e_ref) / e_ref)), "contacts": True}
    print(row, flush=True)
    return row


def write(rows: list[dict], path: Path) -> None:
    lines = [
        "# Visibility on the Cornell box and the open room (sky): its part of the error, and its cost",
        "",
        "Generated by `python -m benchmarks.visibility`. Errors: relative RMS of the user facets' irradiance;",
        "*total* against Mitsuba, *visibility* against the same kernel with `n = 30` (100× the default's rays).",
        "Times: wall seconds of `form_factors` on this 2-core machine, one run each.",
        "",
        "*split* rows: the scene split at its contact lines (`ti.geometry.split_at_contacts`: the floor cut around",
        "the blocks) before `subdivide(k)`, default visibility; *bias*: mean signed relative error. *jittered*: each",
        "quadrature point's rays go to one point per cell at an offset of its own (`visibility_jitter=True`, the",
        "default); *midpoints*: to the cell midpoints (the default before). *weighed sky*: the sky's open part from",
        "its two estimates weighed per facet (`sky_parts.sky_open_parts`, `solver.solve_sky`), its visibility part",
        "against the `n = 30` kernel weighed the same way; elsewhere `lights.sky` (the escaping rays' count where a",
        "facet's row is ray cast).",
        "",
        "| scene | k | facets | visibility | kernel s | rays | total | bias | visibility part | part / total |",
        "|---|---:|---:|---|---:|---:|---:|---:|---:|---:|",
    ]
    for w in rows:
        setting = ("split, " if w["contacts"] else "") + f"n={w['n']}" + (
            f", tol={w['tol']:g}" if w["tol"] is not None else "") + (
            f", angle={w['angle']:g}" if w["angle"] is not None else "") + (
            "" if w["tol"] is not None else ", jittered" if w["jitter"] else ", midpoints") + (
            " (default)" if w["angle"] is not None and w["jitter"] else " (default before)" if w["angle"] else "") + (
            ", weighed sky" if w.get("weighed") else "")
        part = w["visibility"] / w["total"] if w["total"] > 0 else float("nan")
        vis = "–" if w["contacts"] else f"{100 * w['visibility']:.3f} %"
        ratio = "–" if w["contacts"] else f"{part:.2f}"
        lines.append(
            f"| {w['scene']} | {w['k']} | {w['facets']} | {setting} | {w['seconds']:.2f} | {w['rays']:,} | "
            f"{100 * w['total']:.2f} % | {100 * w['bias']:+.2f} % | {vis} | {ratio} |"
        )
    path.write_text("\n".join(lines) + "\n")
    print(f"wrote {path}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="k = 1, 2 only (about a minute)")
    args = ap.parse_args(argv)
    ks = [1, 2] if args.quick else [1, 2, 4]
    torch.set_default_dtype(torch.float64)
    split_only = () if args.quick else (8,)
    rows = [w for name in ("cornell_sky_r9", "cornell_sky_r2") for w in run(name, ks, split_only)]
    room_ks = [1] if args.quick else [1, 2]  # 114 and 456 facets (the n = 30 reference: about a minute at 456)
    rows += [w for name in ("room_sky_r9", "room_sky_r2") for w in run(name, room_ks)]
    write(rows, RESULTS / ("visibility_quick.md" if args.quick else "visibility.md"))


if __name__ == "__main__":
    main()
