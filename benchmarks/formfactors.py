"""Kernel build time and peak memory of ``ti.form_factors`` against the number of facets.

Each configuration runs in a fresh subprocess so that its peak resident memory (``ru_maxrss``) is its own.
Scenes: the paper's 45° V-groove (no facet can block another: no rays) and the Cornell box with its two
blocks (occlusion by ray casting), each with occlusion as chosen by ``"auto"`` and forced the other way.

    python -m benchmarks.formfactors            # ~100, ~1,000 and ~5,000 facets
    python -m benchmarks.formfactors --quick    # ~100 and ~1,000 facets
"""

from __future__ import annotations

import argparse
import json
import time

from benchmarks._common import RESULTS
from benchmarks._common.memory import peak_rss_mb
from benchmarks._common.report import machine, write_lines
from benchmarks._common.workers import run_worker

# (scene, size parameter, occlusion): v-groove divisions per plate edge, Cornell box subdivision
CONFIGS = {
    100: [("v_groove", 7, "auto"), ("v_groove", 7, True), ("cornell_box", 3, "auto"), ("cornell_box", 3, False)],
    1000: [("v_groove", 22, "auto"), ("v_groove", 22, True), ("cornell_box", 8, "auto"),
           ("cornell_box", 8, False)],
    5000: [("v_groove", 50, "auto"), ("cornell_box", 17, "auto"), ("cornell_box", 17, False)],
}


def worker(spec: dict) -> dict:
    import torch

    import torch_interreflect as ti

    torch.set_num_threads(spec["threads"])
    if spec["scene"] == "v_groove":
        scene = ti.scenes.v_groove(45.0, divisions=spec["k"])
    else:
        scene = ti.scenes.cornell_box(divisions=spec["k"])
    t = time.perf_counter()
    K = ti.form_factors(scene, occlusion=spec["occlusion"], progress=False)
    dt = time.perf_counter() - t
    i = K.info
    return {
        "facets": scene.num_facets, "seconds": dt, "pairs": i["pairs"], "points": i["points"],
        "occluded_pairs": i["occluded_pairs"], "rays": i["rays"], "quadrature_s": i["seconds_quadrature"],
        "visibility_s": i["seconds_visibility"], "layout": i["layout"],
        "peak_rss_mb": peak_rss_mb(),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="skip the ~5,000-facet scenes")
    ap.add_argument("--threads", type=int, default=2, help="torch threads per run")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        print(json.dumps(worker(json.loads(args.worker))))
        return
    rows = []
    sizes = [100, 1000] if args.quick else [100, 1000, 5000]
    for size in sizes:
        for scene, k, occ in CONFIGS[size]:
            spec = {"scene": scene, "k": k, "occlusion": occ, "threads": args.threads}
            res = run_worker("benchmarks.formfactors", ["--worker", json.dumps(spec)])
            if "error" in res:
                raise RuntimeError(f"{spec}: {res['error']}")
            res.update(scene=scene, occlusion=occ)
            rows.append(res)
            print(f"{scene:12s} F={res['facets']:5d} occlusion={occ!s:5s}: {res['seconds']:7.2f} s "
                  f"(quadrature {res['quadrature_s']:.2f} s, visibility {res['visibility_s']:.2f} s), "
                  f"{res['pairs']} pairs, {res['points']} points, {res['rays']} rays, "
                  f"peak RSS {res['peak_rss_mb']:.0f} MB", flush=True)
    lines = [
        "# Form-factor kernel: build time and peak memory",
        "",
        f"`python -m benchmarks.formfactors`, {args.threads} torch threads, {machine()}. "
        "Default settings (`tol=1e-6`, 3×3 visibility samples per facet).",
        "Peak RSS is the whole process (Python, torch and the scene included).",
        "",
        "| scene | facets | occlusion | pairs | quadrature points | occluded pairs | rays | quadrature s | "
        "visibility s | total s | peak RSS MB |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['scene']} | {r['facets']} | {r['occlusion']} | {r['pairs']} | {r['points']} | "
            f"{r['occluded_pairs']} | {r['rays']} | {r['quadrature_s']:.2f} | {r['visibility_s']:.2f} | "
            f"{r['seconds']:.2f} | {r['peak_rss_mb']:.0f} |"
        )
    write_lines(RESULTS / "formfactors.md", lines)


if __name__ == "__main__":
    main()
