"""The form-factor kernel alone: torch quadrature (before) vs the fused compiled loop (after), in one run.

For each scene (the 1,024- and 4,624-facet Cornell boxes without the light, the 5,000-facet V-groove) and each
configuration (torch with all threads and no compiled loop, ``TI_DISABLE_NUMBA=1``; fused with 1 thread and with
all threads), one fresh subprocess builds
``form_factors(scene, backend=...)`` with the default settings and reports the quadrature seconds (the kernel),
the visibility seconds, the total, the per-point cost and the peak resident memory added by the call. The
fused-loop floor is measured here too: a serial compiled loop that evaluates the same contour formula for
points given in memory (no rule, no clipping, no Jacobian), i.e. the cheapest any kernel can be per point.
``interreflect generate`` before and after is timed by :mod:`benchmarks.generate_throughput`.

Usage: ``python benchmarks/kernel.py [--quick]`` → ``benchmarks/results/kernel.md``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent
SCENES = {
    "cornell_1024": "ti.scenes.cornell_box(8, light=False)",
    "cornell_4624": "ti.scenes.cornell_box(17, light=False)",
    "v_groove_5000": "ti.scenes.v_groove(45.0, divisions=50)",
}
#: Runs per configuration and pass; the fastest is reported.
REPEATS = 3
QUICK = {
    "cornell_256": "ti.scenes.cornell_box(4, light=False)",
    "cornell_1024": "ti.scenes.cornell_box(8, light=False)",
    "v_groove_968": "ti.scenes.v_groove(45.0, divisions=22)",
}


def floor_ns(n_points: int = 2_000_000) -> float:
    """ns per point of a serial compiled loop of Lambert's contour formula over a quad (1 thread, best of 3)."""
    from numba import njit

    @njit(cache=False)
    def loop(x, normal, quads, which):  # pragma: no cover - compiled
        total = 0.0
        for p in range(x.shape[0]):
            q = quads[which[p]]
            acc = 0.0
            for k in range(4):
                k1 = (k + 1) % 4
                rx, ry, rz = q[k, 0] - x[p, 0], q[k, 1] - x[p, 1], q[k, 2] - x[p, 2]
                sx, sy, sz = q[k1, 0] - x[p, 0], q[k1, 1] - x[p, 1], q[k1, 2] - x[p, 2]
                cx, cy, cz = ry * sz - rz * sy, rz * sx - rx * sz, rx * sy - ry * sx
                cn = math.sqrt(cx * cx + cy * cy + cz * cz)
                if cn > 1e-150:
                    acc += math.atan2(cn, rx * sx + ry * sy + rz * sz) * (
                        cx * normal[p, 0] + cy * normal[p, 1] + cz * normal[p, 2]) / cn
            total += acc
        return total

    rng = np.random.default_rng(0)
    x = rng.random((n_points, 3))
    x[:, 2] = 0.0
    normal = np.zeros((n_points, 3))
    normal[:, 2] = 1.0
    quads = rng.random((1024, 4, 3))
    quads[:, :, 2] = 1.0 + rng.random((1024, 1))
    which = rng.integers(0, 1024, n_points)
    loop(x[:10], normal[:10], quads, which[:10])
    best = math.inf
    for _ in range(3):
        t = time.process_time()
        loop(x, normal, quads, which)
        best = min(best, time.process_time() - t)
    return 1e9 * best / n_points


def one(scene_expr: str, backend: str, threads: int) -> dict:
    """One configuration, in this (fresh) process."""
    import torch

    import torch_interreflect as ti

    torch.set_num_threads(threads)
    scene = eval(scene_expr, {"ti": ti})
    ti.form_factors(ti.scenes.cornell_box(1, dtype=torch.float64), backend=backend)  # load compiled code
    res = {"facets": scene.num_facets}
    for occlusion in (False, "auto"):  # the kernel alone first (its peak memory is the process's first peak)
        best = None
        for rep in range(REPEATS):  # the fastest of REPEATS: wall times on this shared VM vary by ~30 %
            rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
            wall, cpu = time.perf_counter(), time.process_time()
            K = ti.form_factors(scene, backend=backend, occlusion=occlusion, progress=False)
            wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
            if rep == 0:
                peak = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0) / 1024
            if best is None or wall < best[0]:
                best = (wall, cpu, K.info)
            if rep < REPEATS - 1:
                del K
        wall, cpu, info = best
        key = "kernel" if occlusion is False else "occluded"
        res.update({
            f"{key}_pairs": info["pairs"],
            f"{key}_points": info["points"],
            f"{key}_rays": info["rays"],
            f"{key}_quadrature_s": info["seconds_quadrature"],
            f"{key}_visibility_s": info["seconds_visibility"],
            f"{key}_wall_s": wall,
            f"{key}_cpu_s": cpu,
            f"{key}_peak_mb": peak,
            f"{key}_hash": hashlib.sha1(K.to_dense().double().numpy().tobytes()).hexdigest()[:12],
        })
        del K
    return res


def run_one(scene_expr: str, backend: str, threads: int) -> dict:
    # the torch path of before: no compiled loop anywhere (culling and classification included)
    env = dict(os.environ, TI_DISABLE_NUMBA="1" if backend == "torch" else "0")
    out = subprocess.run(
        [sys.executable, __file__, "--one", scene_expr, backend, str(threads)],
        check=True, capture_output=True, text=True, env=env,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smaller scenes (≤ 1,024 facets)")
    ap.add_argument("--one", nargs=3, help=argparse.SUPPRESS)
    ap.add_argument("--out", default=str(ROOT / "results" / "kernel.md"))
    args = ap.parse_args()
    if args.one:
        print(json.dumps(one(args.one[0], args.one[1], int(args.one[2]))))
        return
    all_threads = os.cpu_count() or 1
    floor = floor_ns()
    print(f"fused-loop floor: {floor:.1f} ns/point (1 thread)", flush=True)
    rows = []
    for name, expr in (QUICK if args.quick else SCENES).items():
        res = {}
        for backend, threads in (("torch", all_threads), ("fused", 1), ("fused", all_threads)):
            r = run_one(expr, backend, threads)
            res[(backend, threads)] = r
            print(name, backend, threads, json.dumps(r), flush=True)
        rows.append((name, res))
        write(Path(args.out), rows, floor, all_threads, args.quick)  # partial results survive a stop


def write(path: Path, rows, floor: float, nt: int, quick: bool) -> None:
    load = os.getloadavg()
    lines = [
        "# Form-factor kernel: torch quadrature (before) vs fused compiled loop (after)",
        "",
        f"`python benchmarks/kernel.py{' --quick' if quick else ''}`, one run; {os.cpu_count()} cores, Python "
        f"{platform.python_version()}; load average at the end {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f}. "
        "Other jobs may share the machine: wall times then stretch, CPU seconds (`time.process_time`, all "
        "threads of the process) much less. Default settings (`tol=1e-6`, 3×3 visibility samples); each cell "
        "is a fresh process (compiled code loaded from numba's cache before timing); each pass is run "
        f"{REPEATS} times and the fastest is reported.",
        "",
        f"**Fused-loop floor**: a serial compiled loop of the contour formula over a quad, points already in "
        f"memory: **{floor:.1f} ns/point** (CPU time, 1 thread).",
        "",
        "## The kernel alone (`occlusion=False`: culling, classification and quadrature, no rays)",
        "",
        "*ns/pt* = CPU s of the whole `form_factors` call / quadrature points; *kernel s* = "
        "`info['seconds_quadrature']` (wall); *peak MB*: resident memory the call added.",
        "",
        "| scene | facets | points | path | threads | wall s | CPU s | kernel s | ns/pt | × floor | peak MB "
        "| wall speed-up | CPU speed-up |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, res in rows:
        base = res[("torch", nt)]
        for (backend, threads), r in res.items():
            ns = 1e9 * r["kernel_cpu_s"] / max(r["kernel_points"], 1)
            lines.append(
                f"| {name} | {r['facets']} | {r['kernel_points']:,} | {backend} | {threads} | {r['kernel_wall_s']:.2f} "
                f"| {r['kernel_cpu_s']:.2f} | {r['kernel_quadrature_s']:.2f} | {ns:.0f} | {ns / floor:.1f} | "
                f"{r['kernel_peak_mb']:.0f} | {base['kernel_wall_s'] / r['kernel_wall_s']:.1f}× | "
                f"{base['kernel_cpu_s'] / r['kernel_cpu_s']:.1f}× |"
            )
    lines += [
        "",
        "## With occlusion (`occlusion='auto'`: visibility rays from every quadrature point of blockable pairs)",
        "",
        "| scene | path | threads | rays | kernel s | vis s | wall s | CPU s | wall speed-up | CPU speed-up |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, res in rows:
        base = res[("torch", nt)]
        for (backend, threads), r in res.items():
            lines.append(
                f"| {name} | {backend} | {threads} | {r['occluded_rays']:,} | {r['occluded_quadrature_s']:.2f} | "
                f"{r['occluded_visibility_s']:.2f} | {r['occluded_wall_s']:.2f} | {r['occluded_cpu_s']:.2f} | "
                f"{base['occluded_wall_s'] / r['occluded_wall_s']:.1f}× | "
                f"{base['occluded_cpu_s'] / r['occluded_cpu_s']:.1f}× |"
            )
    lines += ["", f"## Threads: fused, {nt} threads / 1 thread (wall)", "",
              "| scene | kernel s | kernel wall s | vis s | occluded wall s | same bytes |",
              "|---|---|---|---|---|---|"]
    for name, res in rows:
        f1, fn = res[("fused", 1)], res[("fused", nt)]
        same = f1["kernel_hash"] == fn["kernel_hash"] and f1["occluded_hash"] == fn["occluded_hash"]
        lines.append(
            f"| {name} | {fn['kernel_quadrature_s'] / f1['kernel_quadrature_s']:.2f} | "
            f"{fn['kernel_wall_s'] / f1['kernel_wall_s']:.2f} | "
            f"{fn['occluded_visibility_s'] / max(f1['occluded_visibility_s'], 1e-9):.2f} | "
            f"{fn['occluded_wall_s'] / f1['occluded_wall_s']:.2f} | {'yes' if same else 'NO'} |"
        )
    path.write_text("\n".join(lines) + "\n")
    print(path.read_text())


if __name__ == "__main__":
    main()
