"""Benchmark of :func:`torch_interreflect.solve.solve`: dense LU vs conjugate gradients vs Neumann vs the paper's
literal block formulation.

Run ``python -m benchmarks.solver`` (``--quick`` for a reduced run). Writes ``benchmarks/results/solver.md``
and ``benchmarks/results/solver.png``.

Form factors: a closed box room (cells on the six inner walls, box sides proportional to the cell counts, so
every cell is a unit square), centre-point kernel ``F_ij = cosθ_i cosθ_j A_j / (π d²)`` between cells of
different walls (0 on the same wall), then symmetrically rescaled (``D W D``, ``W_ij = A_i F_ij``) so every
row sums to 1: a closed enclosure, reciprocal, with the spread spectrum of a real scene (not rank one like the
sphere interior). F ∈ {256, 1024, 4096} are the boxes 4×8×8, 8×16×16, 16×32×32 cells.

Columns: reflectance ``[B, F, L]`` with L = 31 wavelengths and B = N / 31 scenes, drawn uniformly in
``[r_max/2, r_max]`` independently per facet, wavelength and batch element (so every column is distinct: the
dense method factors N matrices); ``E0`` uniform random. float32.

Memory: each configuration runs in its own subprocess (inputs loaded from a file the parent wrote); "peak MiB"
is the growth of the resident-set high-water mark (``VmHWM``, reset through ``/proc/self/clear_refs``) over the
first forward+backward run above the resident set before it — real process memory, not an analytic count.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import tempfile
import time
from pathlib import Path

import torch

from benchmarks._common import RESULTS
from benchmarks._common.memory import peak_since, reset_peak
from benchmarks._common.report import write_lines
from benchmarks._common.timing import best_time
from benchmarks._common.workers import run_worker

BOXES = {256: (4, 8, 8), 1024: (8, 16, 16), 4096: (16, 32, 32)}
L = 31
DTYPE = torch.float32
TOL = 1e-6
# a configuration whose estimated time exceeds this is skipped (and reported as skipped)
MAX_EST_SECONDS = 25.0


def box_room(nx: int, ny: int, nz: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Form factors (closed, reciprocal, row sums 1) and areas of a box room with unit-square wall cells."""
    centres, normals = [], []
    dims = (nx, ny, nz)
    for axis in range(3):
        u, v = [a for a in range(3) if a != axis]
        iu, iv = torch.meshgrid(torch.arange(dims[u]) + 0.5, torch.arange(dims[v]) + 0.5, indexing="ij")
        for side in (0.0, float(dims[axis])):
            c = torch.zeros(iu.numel(), 3, dtype=torch.float64)
            c[:, u], c[:, v], c[:, axis] = iu.reshape(-1), iv.reshape(-1), side
            nrm = torch.zeros(iu.numel(), 3, dtype=torch.float64)
            nrm[:, axis] = 1.0 if side == 0 else -1.0
            centres.append(c)
            normals.append(nrm)
    c, n = torch.cat(centres), torch.cat(normals)
    d = c[None, :, :] - c[:, None, :]
    d2 = (d * d).sum(-1)
    same = (n[:, None, :] * n[None, :, :]).sum(-1) > 0.5
    d2 = torch.where(same, torch.ones_like(d2), d2)
    cos_i = ((d * n[:, None, :]).sum(-1) / d2.sqrt()).clamp_min(0)
    cos_j = (-(d * n[None, :, :]).sum(-1) / d2.sqrt()).clamp_min(0)
    w = torch.where(same, torch.zeros_like(d2), cos_i * cos_j / (math.pi * d2))  # A_i F_ij, unit areas
    areas = torch.ones(c.shape[0], dtype=torch.float64)
    s = torch.ones_like(areas)
    for _ in range(200):  # symmetric Sinkhorn: D W D has row sums A
        s = torch.sqrt(s * areas / (w @ s))
    w = s[:, None] * w * s[None, :]
    return w / areas[:, None], areas


def _cols(t: torch.Tensor) -> torch.Tensor:
    return t.movedim(-2, 0).reshape(t.shape[-2], -1)


def worker(cfg: dict) -> dict:
    """One configuration, run in a fresh process so that its memory high-water mark is its own."""
    import warnings

    from torch_interreflect import FormFactors
    from torch_interreflect.solver import solve, solve_with_info
    from torch_interreflect.solver.columns import solve_columns
    from torch_interreflect.solver.plan import Stats, get_plan

    nf, ncol, rmax, method = cfg["F"], cfg["N"], cfg["rmax"], cfg["method"]
    torch.manual_seed(0)
    f, areas = torch.load(cfg["path"])  # built by the parent: building here would raise the high-water mark
    ff = FormFactors(f, areas)
    b = ncol // L
    r = (rmax * (0.5 + 0.5 * torch.rand(b, nf, L))).to(DTYPE)
    e0 = torch.rand(b, nf, L, dtype=DTYPE)
    out: dict = dict(cfg)
    reps = cfg.get("reps", 1)
    if method == "literal":
        # the paper's eq. 58/68: radiosity B = (R_ext^-1 - K_ext)^-1 E0 with K_ext = I_L (x) F, one
        # (F L) x (F L) system per batch element (solved by LU, cheaper than forming the inverse)
        def fwd():
            kext = torch.kron(torch.eye(L, dtype=DTYPE), ff.matrix)
            outs = []
            for k in range(b):
                rext = r[k].T.reshape(-1)
                m = torch.diag(1 / rext) - kext
                bk = torch.linalg.solve(m, e0[k].T.reshape(-1, 1))
                outs.append((bk.reshape(-1) / rext).reshape(L, nf).T)
            return torch.stack(outs)

        rss0 = reset_peak()
        fwd()
        out["peak_mib"] = peak_since(rss0)
        out["fwd_s"] = best_time(fwd, reps)
        out["fwdbwd_s"] = None
        out["flops"] = b * (2 / 3) * (nf * L) ** 3
        return out

    def fwdbwd():
        rr = r.clone().requires_grad_()
        ee = e0.clone().requires_grad_()
        solve(ff, rr, ee, method=method, tol=TOL).sum().backward()

    def timed(fn) -> float:
        t0 = time.perf_counter()
        fn()
        return time.perf_counter() - t0

    get_plan(ff)  # per-scene, cached: not part of the solve
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rss0 = reset_peak()
        t_fb = timed(fwdbwd)  # first run: memory high-water mark of forward+backward
        out["peak_mib"] = peak_since(rss0)
        t0 = time.perf_counter()
        _, info = solve_with_info(ff, r, e0, method=method, tol=TOL)
        t_f = time.perf_counter() - t0
        out["iterations"] = info.iterations
        out["fwd_s"] = min(t_f, best_time(lambda: solve(ff, r, e0, method=method, tol=TOL), reps - 1))
        out["fwdbwd_s"] = min(t_fb, best_time(fwdbwd, reps - 1))
        # adjoint iterations (the backward solve), counted on the private core with a random upstream gradient
        st = Stats()
        if method != "dense":
            solve_columns(
                ff.matrix,
                get_plan(ff),
                ff.areas,
                _cols(r),
                _cols(torch.rand_like(e0)),
                transpose=True,
                method=method,
                tol=TOL,
                max_iter=100_000,
                stats=st,
            )
        out["adjoint_iterations"] = st.iterations
    g = ff.matrix
    x = torch.rand(nf, ncol, dtype=DTYPE)
    out["mm_s"] = best_time(lambda: g @ x, 5)
    mm_flops = 2 * nf * nf * ncol
    if method == "dense":
        out["flops"] = ncol * (2 / 3) * nf**3 + 2 * mm_flops
    else:
        out["flops"] = (out["iterations"] + 2) * mm_flops
    return out


def estimate_seconds(nf: int, ncol: int, rmax: float, method: str, rates: dict) -> float:
    mm = 2 * nf * nf * ncol / rates["gemm"]
    if method == "dense":
        return 1.2 * ncol * (2 / 3) * nf**3 / rates["lu"] + 4 * mm
    if method == "literal":
        n = nf * L
        if 4 * n * n * 2 > 8e9:
            return math.inf
        return (ncol // L) * (2 / 3) * n**3 / rates["lu"]
    if method == "cg":  # iterations: 0.35 x the worst-case bound (as measured on the room, see AUTO_COST)
        k = 0.35 * 0.5 * math.sqrt((1 + rmax) / (1 - rmax)) * math.log(2 / TOL) + 3
        return 2.5 * k * mm
    k = math.log(TOL) / math.log(0.8 * rmax)  # reflectance is uniform in [r_max/2, r_max]
    return 2.5 * k * mm


def measure_rates() -> dict:
    a = torch.rand(2048, 2048, dtype=DTYPE)
    gemm = 2 * 2048**3 / best_time(lambda: a @ a, 3)
    m = torch.rand(8, 512, 512, dtype=DTYPE) + 512 * torch.eye(512, dtype=DTYPE)
    lu = 8 * (2 / 3) * 512**3 / best_time(lambda: torch.linalg.lu_factor_ex(m), 3)
    return {"gemm": gemm, "lu": lu}


CAL_BOXES = {16: (1, 2, 2), 40: (2, 2, 4), 64: (2, 4, 4), 144: (3, 6, 6), 256: (4, 8, 8), 576: (6, 12, 12)}


def calibrate() -> None:
    """Time dense vs cg (forward, float64, r_max = 0.9) on small rooms: the crossover behind ``AUTO_COST``."""
    import warnings

    from torch_interreflect import FormFactors
    from torch_interreflect.solver import solve, solve_with_info
    from torch_interreflect.solver.method import choose_method
    from torch_interreflect.solver.plan import get_plan

    print("| F | N | distinct K | dense ms | cg ms | cg iters | faster | auto picks |")
    print("|---|---|---|---|---|---|---|---|")
    for nf, box in CAL_BOXES.items():
        f, areas = box_room(*box)
        ff = FormFactors(f, areas)
        for ncol in (1, 31, 248):
            for grey in (True, False):
                if grey and ncol == 1:
                    continue
                torch.manual_seed(0)
                r = 0.9 * (0.5 + 0.5 * torch.rand(nf, 1 if grey else ncol, dtype=torch.float64))
                r = r.expand(nf, ncol)
                e0 = torch.rand(nf, ncol, dtype=torch.float64)
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    td = best_time(lambda ff=ff, r=r, e0=e0: solve(ff, r, e0, method="dense"), 3)
                    tc = best_time(lambda ff=ff, r=r, e0=e0: solve(ff, r, e0, method="cg"), 3)
                    _, info = solve_with_info(ff, r, e0, method="cg")
                pick = choose_method(get_plan(ff), r, 1e-6)
                k = 1 if grey else ncol
                best = "dense" if td < tc else "cg"
                it = info.iterations
                print(f"| {nf} | {ncol} | {k} | {td * 1e3:.2f} | {tc * 1e3:.2f} | {it} | {best} | {pick} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="F in {256, 1024}, N = 248, r_max = 0.9 only")
    ap.add_argument("--calibrate", action="store_true", help="time dense vs cg on small rooms (auto crossover)")
    ap.add_argument("--threads", type=int, default=0, help="torch threads (default: torch's own choice)")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.calibrate:
        calibrate()
        return
    if args.worker:
        print(json.dumps(worker(json.loads(args.worker))))
        return
    env = dict(os.environ)
    if args.threads:
        torch.set_num_threads(args.threads)
        env["OMP_NUM_THREADS"] = str(args.threads)
    rates = measure_rates()
    print(
        f"matmul peak (2048^3 GEMM, {DTYPE}): {rates['gemm'] / 1e9:.1f} GFLOP/s; "
        f"batched LU: {rates['lu'] / 1e9:.1f} GFLOP/s; threads {torch.get_num_threads()}"
    )
    sizes = [256, 1024] if args.quick else [256, 1024, 4096]
    cols = [248] if args.quick else [31, 248]
    rmaxes = [0.9] if args.quick else [0.5, 0.9, 0.99]
    methods = ["dense", "cg", "neumann", "literal"]
    rows = []
    tmp = Path(tempfile.mkdtemp(prefix="ti_bench_"))
    paths = {}
    for nf in sizes:
        f, areas = box_room(*BOXES[nf])
        paths[nf] = str(tmp / f"room{nf}.pt")
        torch.save((f.to(DTYPE), areas.to(DTYPE)), paths[nf])
        del f, areas
    for nf in sizes:
        for ncol in cols:
            for rmax in rmaxes:
                for method in methods:
                    if method == "literal" and rmax != 0.9:
                        continue  # same cost at every r_max
                    if method == "dense" and rmax != 0.9 and not args.quick:
                        # cost does not depend on r_max: time once, copy
                        continue
                    est = estimate_seconds(nf, ncol, rmax, method, rates)
                    cfg = {
                        "F": nf,
                        "N": ncol,
                        "rmax": rmax,
                        "method": method,
                        "reps": 3 if est < 2 else 1,
                        "path": paths[nf],
                    }
                    if est > (60.0 if method == "literal" else MAX_EST_SECONDS):
                        why = "does not fit in memory" if math.isinf(est) else f"estimated {est:.0f} s"
                        cfg.pop("path")
                        rows.append({**cfg, "skipped": why})
                        print(f"skip {cfg}: {why}")
                        continue
                    res = run_worker("benchmarks.solver", ["--worker", json.dumps(cfg)], env=env)
                    if "error" in res:
                        cfg.pop("path")
                        rows.append({**cfg, "skipped": "failed: " + str(res["error"])[:80]})
                        print(res["error"])
                        continue
                    res.pop("path", None)
                    rows.append(res)
                    print(json.dumps(res))
    shutil.rmtree(tmp, ignore_errors=True)
    # dense cost does not depend on r_max: copy the r_max = 0.9 row to the others
    if not args.quick:
        extra = []
        for row in rows:
            if row["method"] == "dense" and row["rmax"] == 0.9:
                for rm in (0.5, 0.99):
                    extra.append({**row, "rmax": rm, "copied": True})
        rows += extra
    write(rows, rates, args.quick)


def write(rows: list[dict], rates: dict, quick: bool) -> None:
    RESULTS.mkdir(exist_ok=True)
    key = {"dense": 0, "cg": 1, "neumann": 2, "literal": 3}
    rows.sort(key=lambda r: (r["F"], r["N"], r["rmax"], key[r["method"]]))
    lines = [
        "# Solver benchmark",
        "",
        f"`python -m benchmarks.solver{' --quick' if quick else ''}`; {DTYPE}, tol {TOL}, "
        f"{torch.get_num_threads()} threads. Matmul peak measured in the same run (2048³ GEMM): "
        f"**{rates['gemm'] / 1e9:.1f} GFLOP/s**; batched LU 512: {rates['lu'] / 1e9:.1f} GFLOP/s.",
        "",
        "Form factors: closed box room, centre-point kernel, rescaled to row sums 1 (see the script). "
        "Reflectance `[B, F, 31]` uniform in [r_max/2, r_max], every column distinct. Peak = growth of "
        "the resident-set high-water mark (VmHWM, reset via /proc/self/clear_refs) over the first forward+backward "
        "run in a fresh subprocess (real RSS, not an analytic count). "
        "`iters` = forward / adjoint iterations. `mm` = one `[F,F] @ [F,N]` product; `fwd/(iters·mm)` is the "
        "CG overhead factor. literal = the paper's `(R_ext⁻¹ − K_ext)⁻¹` with `(F·31)²` block matrices "
        "(solved by LU per batch element; forward only).",
        "",
        "| F | N=B·L | r_max | method | fwd s | fwd+bwd s | peak MiB | iters | GFLOP/s (fwd) | % peak | "
        "fwd/(iters·mm) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        head = f"| {r['F']} | {r['N']} | {r['rmax']} | {r['method']} |"
        if "skipped" in r:
            lines.append(f"{head} skipped: {r['skipped']} | | | | | | |")
            continue
        gf = r["flops"] / r["fwd_s"] / 1e9
        it = f"{r.get('iterations', '')}/{r.get('adjoint_iterations', '')}" if r["method"] in ("cg", "neumann") else ""
        ratio = (
            f"{r['fwd_s'] / (r['iterations'] * r['mm_s']):.2f}"
            if r["method"] in ("cg", "neumann") and r.get("iterations")
            else ""
        )
        fb = f"{r['fwdbwd_s']:.3f}" if r.get("fwdbwd_s") is not None else "–"
        copied = " (same as 0.9)" if r.get("copied") else ""
        lines.append(
            f"{head} {r['fwd_s']:.3f}{copied} | {fb} | {r['peak_mib']:.0f} | {it} | {gf:.1f} | "
            f"{100 * gf / (rates['gemm'] / 1e9):.0f} | {ratio} |"
        )
    # the target check
    lines += ["", "## Target: F = 1024, N = 248, r_max = 0.9", ""]
    sel = {r["method"]: r for r in rows if r["F"] == 1024 and r["N"] == 248 and r["rmax"] == 0.9 and "skipped" not in r}
    if "cg" in sel and "dense" in sel:
        cg, de = sel["cg"], sel["dense"]
        speed = de["fwdbwd_s"] / cg["fwdbwd_s"]
        budget = (cg["iterations"] + cg["adjoint_iterations"]) * cg["mm_s"]
        lines.append(
            f"- cg forward+backward {cg['fwdbwd_s']:.3f} s vs dense {de['fwdbwd_s']:.3f} s: "
            f"**{speed:.1f}×** faster (target ≥ 5×: {'reached' if speed >= 5 else 'NOT reached'})."
        )
        lines.append(
            f"- cg forward+backward vs (forward + adjoint iterations = "
            f"{cg['iterations'] + cg['adjoint_iterations']}) × one product ({cg['mm_s'] * 1e3:.2f} ms) = "
            f"{budget:.3f} s: **{cg['fwdbwd_s'] / budget:.2f}×** (target ≤ 2×: "
            f"{'reached' if cg['fwdbwd_s'] / budget <= 2 else 'NOT reached'})."
        )
    write_lines(RESULTS / "solver.md", lines)
    print("\n".join(lines))
    plot(rows)


def plot(rows: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ncols = sorted({r["N"] for r in rows})
    fig, axes = plt.subplots(1, len(ncols), figsize=(5 * len(ncols), 3.6), squeeze=False)
    for ax, ncol in zip(axes[0], ncols, strict=False):
        for method, style in (("dense", "k-o"), ("cg", "b-s"), ("neumann", "g-^"), ("literal", "r-x")):
            for rmax, alpha in ((0.5, 0.4), (0.9, 1.0), (0.99, 0.7)):
                pts = [
                    (r["F"], r["fwdbwd_s"] or r["fwd_s"])
                    for r in rows
                    if r["N"] == ncol
                    and r["method"] == method
                    and r["rmax"] == rmax
                    and "skipped" not in r
                    and not r.get("copied")
                ]
                if pts:
                    xs, ys = zip(*sorted(pts), strict=False)
                    ax.loglog(xs, ys, style, alpha=alpha, label=f"{method} r={rmax}", ms=4)
        ax.set_title(f"N = B·L = {ncol}")
        ax.set_xlabel("facets F")
        ax.set_ylabel("forward+backward s (literal: forward)")
        ax.grid(True, which="both", alpha=0.3)
    axes[0][-1].legend(fontsize=6, ncol=2)
    fig.tight_layout()
    fig.savefig(RESULTS / "solver.png", dpi=90)


if __name__ == "__main__":
    main()
