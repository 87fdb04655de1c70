"""Hierarchical form factors (``ti.hierarchical_form_factors``): error against the dense kernel, and scaling.

(a) **Error** on scenes where the dense kernel fits (~1,000 and ~5,000 facets): relative RMS error of a product
    ``F x`` (random ``x``), per-facet relative RMSE and max error of the row sums and of the solved irradiance
    ``E`` (grey reflectance 0.5 and 0.9, the scene's area light: the Cornell box's ``light``, the room's ``lamp``;
    ``E0`` from the dense kernel so that only the operator differs), for several ``eta``; time and peak RSS of both.
(b) **Scaling**: Cornell box and room at about 1k, 5k, 20k and 50k facets (``eta = 0.5``): kernel time, solve time
    (31 wavelengths, ``method="cg"``), peak RSS, near-field nnz, far blocks.

Every point runs in a fresh subprocess, so its peak resident memory (``VmHWM``) is its own. Results go to
``benchmarks/results/hierarchical{,_quick}.{md,png}``.

    python -m benchmarks.hierarchical               # full run (the 50k-facet points take a few minutes each)
    python -m benchmarks.hierarchical --quick       # small scenes only (~2 min)
    python -m benchmarks.hierarchical --error-only  # (a) alone, to hierarchical_error.md (~2 min)
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from pathlib import Path

from benchmarks._common import RESULTS
from benchmarks._common.memory import peak_rss_mb
from benchmarks._common.report import write_lines
from benchmarks._common.workers import run_worker

ETAS = (0.3, 0.5, 0.7)
# scene -> size parameters: Cornell box subdivision, room facets per metre
ERROR_SIZES = {"cornell_box": (8, 17), "room": (3.3, 7.2)}
SCALE_SIZES = {"cornell_box": (8, 17, 34, 54), "room": (3.3, 7.2, 14.3, 22.7)}
QUICK_ERROR = {"cornell_box": (6,), "room": (2.5,)}
QUICK_SCALE = {"cornell_box": (4, 8), "room": (2.0, 3.3)}
LIGHT = {"cornell_box": "light", "room": "lamp"}


def build(scene: str, k: float):
    import torch

    import torch_interreflect as ti

    if scene == "cornell_box":
        return ti.scenes.cornell_box(divisions=int(k), dtype=torch.float64)
    return ti.scenes.room(divisions=float(k), dtype=torch.float64)


def _columns(n: int):
    import torch

    g = torch.Generator().manual_seed(0)
    return torch.rand(n, 4, dtype=torch.float64, generator=g)


def worker_dense(spec: dict) -> dict:
    import numpy as np
    import torch

    import torch_interreflect as ti

    torch.set_num_threads(spec["threads"])
    scene = build(spec["scene"], spec["k"])
    t = time.perf_counter()
    K = ti.form_factors(scene, progress=False)
    t_kernel = time.perf_counter() - t
    e0 = ti.lights.light_geometry(scene, K, LIGHT[spec["scene"]])[:, None]
    out = {"prod": K.matmul(_columns(scene.num_facets)).numpy(), "rows": K.row_sums().numpy(), "e0": e0.numpy()}
    t = time.perf_counter()
    for r in (0.5, 0.9):
        out[f"E{r}"] = ti.solve(K, torch.full((scene.num_facets,), r, dtype=torch.float64), e0).numpy()
    t_solve = time.perf_counter() - t
    np.savez(spec["out"], **out)
    return {"facets": scene.num_facets, "kernel_s": t_kernel, "solve_s": t_solve, "peak_rss_mb": peak_rss_mb(),
            "nnz": K.nnz}


def _rel(a, b, floor: float) -> tuple[float, float]:
    import numpy as np

    d = np.abs(a - b) / np.maximum(np.abs(b), floor)
    return float(np.sqrt(np.mean(d**2))), float(d.max())


def worker_hier(spec: dict) -> dict:
    import numpy as np
    import torch

    import torch_interreflect as ti

    torch.set_num_threads(spec["threads"])
    scene = build(spec["scene"], spec["k"])
    t = time.perf_counter()
    H = ti.hierarchical_form_factors(scene, eta=spec["eta"], progress=False)
    t_kernel = time.perf_counter() - t
    i = H.info
    res = {"facets": scene.num_facets, "kernel_s": t_kernel, "near_nnz": i["near_nnz"], "far_blocks": i["far_blocks"],
           "rays": i["rays"], "bytes": i["bytes"], "estimated_rel_error": i["estimated_rel_error"],
           "near_s": i["seconds_near"], "tree_traversal_s": i["seconds_tree"] + i["seconds_traversal"],
           "far_visibility_s": i["seconds_far_visibility"]}
    n = scene.num_facets
    if spec.get("dense"):
        ref = np.load(spec["dense"])
        p = H.matmul(_columns(n)).numpy()
        res["prod_rel_rms"] = float(np.linalg.norm(p - ref["prod"]) / np.linalg.norm(ref["prod"]))
        res["rows_rmse"], res["rows_max"] = _rel(H.row_sums().numpy(), ref["rows"], 0.05)
        e0 = torch.as_tensor(ref["e0"])
        for r in (0.5, 0.9):
            E = ti.solve(H, torch.full((n,), r, dtype=torch.float64), e0, method="cg").numpy()
            floor = 1e-3 * float(np.abs(ref[f"E{r}"]).max())
            res[f"E{r}_rmse"], res[f"E{r}_max"] = _rel(E, ref[f"E{r}"], floor)
    else:
        # 31 wavelengths, reflectance varying over facets and wavelengths, the scene's area light
        lam = torch.linspace(0, 1, 31, dtype=torch.float64)
        ph = torch.rand(n, 1, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
        refl = 0.2 + 0.6 * (0.5 + 0.5 * torch.cos(6.0 * lam[None, :] + 6.0 * ph))
        g = ti.lights.light_geometry(scene, H, LIGHT[spec["scene"]])
        e0 = g[:, None] * torch.ones(31, dtype=torch.float64)
        t = time.perf_counter()
        _, info = ti.solver.solve_with_info(H, refl, e0, method="cg", tol=1e-6)
        res["solve_s"] = time.perf_counter() - t
        res["iterations"] = info.iterations
    res["peak_rss_mb"] = peak_rss_mb()
    return res


def run(spec: dict) -> dict:
    return run_worker("benchmarks.hierarchical", ["--worker", json.dumps(spec)])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="small scenes only")
    ap.add_argument("--threads", type=int, default=2, help="torch threads per run")
    ap.add_argument("--error-only", action="store_true", help="(a) alone, written to hierarchical_error.md")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        spec = json.loads(args.worker)
        print(json.dumps(worker_dense(spec) if spec["kind"] == "dense" else worker_hier(spec)))
        return
    err_sizes = QUICK_ERROR if args.quick else ERROR_SIZES
    scale_sizes = {} if args.error_only else QUICK_SCALE if args.quick else SCALE_SIZES
    etas = (0.3, 0.5) if args.quick else ETAS
    err_rows, scale_rows = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for scene, sizes in err_sizes.items():
            for k in sizes:
                path = str(Path(tmp) / f"{scene}_{k}.npz")
                d = run({"kind": "dense", "scene": scene, "k": k, "threads": args.threads, "out": path})
                print(f"dense {scene} k={k}: {d}", flush=True)
                for eta in etas:
                    h = run({"kind": "hier", "scene": scene, "k": k, "eta": eta, "threads": args.threads,
                             "dense": path})
                    print(f"  hier eta={eta}: {h}", flush=True)
                    err_rows.append({"scene": scene, "k": k, "eta": eta, "dense": d, "hier": h})
    for scene, sizes in scale_sizes.items():
        for k in sizes:
            h = run({"kind": "hier", "scene": scene, "k": k, "eta": 0.5, "threads": args.threads})
            print(f"scale {scene} k={k}: {h}", flush=True)
            scale_rows.append({"scene": scene, "k": k, "hier": h})
    write(err_rows, scale_rows, args)


def write(err_rows: list, scale_rows: list, args: argparse.Namespace) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    suffix = ("_error" if args.error_only else "") + ("_quick" if args.quick else "")
    RESULTS.mkdir(exist_ok=True)
    lines = [
        "# Hierarchical form factors: error against the dense kernel, and scaling",
        "",
        f"`python -m benchmarks.hierarchical{' --quick' if args.quick else ''}"
        f"{' --error-only' if args.error_only else ''}`, {args.threads} torch threads, CPU "
        f"({platform.processor() or platform.machine()}), Python {platform.python_version()}, float64. "
        "Default settings otherwise (`leaf_size=16`, `order=1`, `quadrature_tol=1e-6`, occlusion `auto`). Every point "
        "is its own subprocess; peak RSS is that process's `VmHWM` (Python, torch and the scene included).",
        "",
        "## (a) Error against the dense kernel",
        "",
        "Product: relative RMS error of `F x` (4 random columns). Row sums and `E`: per-facet relative RMSE / max "
        "(row sums relative to max(Σ_j F_ij, 0.05); `E` relative to max(E, 1e-3 max E)). `E`: grey reflectance r, the "
        "scene's area light (`E0` from the dense kernel), `method=\"cg\"`. `est.`: `info[\"estimated_rel_error\"]`.",
        "",
        "| scene | facets | eta | product | row sums RMSE / max | E r=0.5 RMSE / max | E r=0.9 RMSE / max | est. "
        "| hier kernel s | hier RSS MB | near nnz | far blocks | dense kernel s | dense RSS MB | dense nnz |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in err_rows:
        h, d = row["hier"], row["dense"]
        if "error" in h or "error" in d:
            lines.append(f"| {row['scene']} | | {row['eta']} | failed: {h.get('error') or d.get('error')} |")
            continue
        lines.append(
            f"| {row['scene']} | {h['facets']} | {row['eta']} | {h['prod_rel_rms']:.2%} | "
            f"{h['rows_rmse']:.2%} / {h['rows_max']:.1%} | {h['E0.5_rmse']:.2%} / {h['E0.5_max']:.1%} | "
            f"{h['E0.9_rmse']:.2%} / {h['E0.9_max']:.1%} | {h['estimated_rel_error']:.2%} | {h['kernel_s']:.1f} | "
            f"{h['peak_rss_mb']:.0f} | {h['near_nnz']} | {h['far_blocks']} | {d['kernel_s']:.1f} | "
            f"{d['peak_rss_mb']:.0f} | {d['nnz']} |"
        )
    if args.error_only:
        write_lines(RESULTS / f"hierarchical{suffix}.md", lines)
        print((RESULTS / f"hierarchical{suffix}.md").read_text())
        return
    lines += [
        "",
        "## (b) Scaling (eta = 0.5)",
        "",
        "Solve: 31 wavelengths, reflectance varying over facets and wavelengths in [0.2, 0.8], the area light, "
        "`method=\"cg\"`, `tol=1e-6`.",
        "",
        "| scene | facets | kernel s | (near s) | solve s | CG iterations | peak RSS MB | operator MB | near nnz | "
        "far blocks | rays |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in scale_rows:
        h = row["hier"]
        if "error" in h:
            lines.append(f"| {row['scene']} | k={row['k']} | failed: {h['error']} (rc {h['returncode']}) |")
            continue
        lines.append(
            f"| {row['scene']} | {h['facets']} | {h['kernel_s']:.1f} | {h['near_s']:.1f} | {h['solve_s']:.2f} | "
            f"{h['iterations']} | {h['peak_rss_mb']:.0f} | {h['bytes'] / 2**20:.0f} | {h['near_nnz']} | "
            f"{h['far_blocks']} | {h['rays']} |"
        )
    write_lines(RESULTS / f"hierarchical{suffix}.md", lines)

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for scene, marker in (("cornell_box", "o"), ("room", "s")):
        rows = [r["hier"] for r in scale_rows if r["scene"] == scene and "error" not in r["hier"]]
        if rows:
            f = [r["facets"] for r in rows]
            axes[0].loglog(f, [r["kernel_s"] for r in rows], marker + "-", label=f"{scene}: hierarchical kernel")
            axes[0].loglog(f, [r["solve_s"] for r in rows], marker + ":", label=f"{scene}: solve (31 λ, cg)")
            axes[1].loglog(f, [r["peak_rss_mb"] for r in rows], marker + "-", label=f"{scene}: hierarchical")
        dense = {r["dense"]["facets"]: r["dense"] for r in err_rows
                 if r["scene"] == scene and "error" not in r["dense"]}
        if dense:
            f = sorted(dense)
            axes[0].loglog(f, [dense[x]["kernel_s"] for x in f], marker + "--", label=f"{scene}: dense kernel")
            axes[1].loglog(f, [dense[x]["peak_rss_mb"] for x in f], marker + "--", label=f"{scene}: dense")
    axes[0].set(xlabel="facets", ylabel="seconds", title="time")
    axes[1].set(xlabel="facets", ylabel="peak RSS (MB)", title="memory")
    for ax in axes:
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(RESULTS / f"hierarchical{suffix}.png", dpi=110)
    print((RESULTS / f"hierarchical{suffix}.md").read_text())


if __name__ == "__main__":
    main()
