"""Speed against error: this library against Mitsuba 3, the paper's Monte Carlo kernel and the n-bounce model.

For every cached reference (``benchmarks/references/``, made by ``mitsuba_ref.py references``: per-facet
irradiance of the built-in scenes from Mitsuba 3 at millions of paths per facet) it times

* this library: ``form_factors`` (contour quadrature) + direct light + ``solve``, on the scene refined by
  ``Scene.subdivide(k)`` and area-averaged back onto the reference's facets, at several refinements,
  quadrature tolerances and solver tolerances, and with 2, 3, 4 and ∞ bounces;
* the paper's Monte Carlo kernel (``form_factors(method="monte_carlo", rays_per_facet=n)``) at several ``n``;
* Mitsuba 3 (``path`` integrator, irradiance-meter estimator batched over facets) at several sample counts,

on the same machine in the same run, and reports per-facet relative RMSE and max error against the reference,
kernel, solve and total time, and Mitsuba's time at our error (interpolated on its time-against-error curve).
A spectral variant (31 wavelengths, camera RGB of a Nikon D5100) compares against Mitsuba's
``llvm_ad_spectral``. A scaling section measures time and peak memory against facets, wavelengths and batch.

Usage::

    .venv/bin/python -m benchmarks.speed_vs_error --quick     # make bench: a subset, under 10 minutes
    .venv/bin/python -m benchmarks.speed_vs_error             # the full run (about an hour on 2 cores)

Writes ``benchmarks/results/speed_vs_error[_quick].md`` and PNG plots beside it. Needs the cached references;
Mitsuba rows need the ``bench`` extra (they are skipped, with a note, when Mitsuba is not installed).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

# OpenMP threads that spin while they wait turn a busy CPU into 5-50x slower, erratic timings on a shared
# machine; passive waiting costs little when the machine is idle. Must be set before torch loads OpenMP.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch

import torch_interreflect as ti
from benchmarks._common import RESULTS
from benchmarks._common import mitsuba as mr
from benchmarks._common.memory import mem_available, status_mb
from benchmarks._common.ours import DTYPE, direct_light, solve
from benchmarks._common.report import debias, fmt_e, fmt_t, loadavg, rel_errors, write_lines
from benchmarks._common.timing import timed
from benchmarks._common.workers import run_worker


# ---------------------------------------------------------------------------------------------- records
@dataclass
class Row:
    scene: str
    method: str  # "ours", "ours n-bounce", "MC kernel", "Mitsuba 3", ...
    setting: str
    facets: int  # facets actually computed on
    kernel_s: float
    solve_s: float
    rmse: float  # per-facet relative RMSE against the reference
    max_err: float
    extra: dict = field(default_factory=dict)

    @property
    def total_s(self) -> float:
        return self.kernel_s + self.solve_s


# ---------------------------------------------------------------------------------------------- ours
#: Kernels (form factors and direct light) by geometry, light and settings: the r = 0.9 and r = 0.2
#: references of a scene share them, so each is computed (and timed) once.
_KERNELS: dict[tuple, tuple[Any, Any, Any, Any, float]] = {}


class Ours:
    """This library on one reference scene: kernels cached per (refinement, method, setting)."""

    def __init__(self, name: str, ref: dict) -> None:
        self.name = name
        self.ref = ref
        self.spec = ref["settings"]
        self.scene = mr.build_scene(self.spec)
        self.r = float(self.spec["reflectance"])
        self.light = self.spec["light"]
        self.solve = solve
        self._geometry = json.dumps([self.spec["builder"], self.spec["kwargs"], self.light], sort_keys=True)

    def kernel(self, k: int, method: str = "quadrature", tol: float = 1e-6, samples: int = 0, seed: int = 0):
        key = (self._geometry, k, method, tol, samples, seed)
        if key not in _KERNELS:

            def run() -> tuple:
                fine, parent = self.scene.subdivide(k)
                if method == "quadrature":
                    K = ti.form_factors(fine, quadrature_tol=tol, progress=False)
                else:
                    g = torch.Generator().manual_seed(seed)
                    K = ti.form_factors(fine, method="monte_carlo", rays_per_facet=samples, generator=g, progress=False)
                E0 = direct_light(fine, K, self.light)
                return fine, parent, K, E0

            (fine, parent, K, E0), dt = timed(run, budget=10.0, reps=2)
            _KERNELS[key] = (fine, parent, K, E0, dt)
        return _KERNELS[key]

    def row(
        self,
        method: str,
        setting: str,
        k: int = 1,
        *,
        kmethod: str = "quadrature",
        ff_tol: float = 1e-6,
        samples: int = 0,
        seed: int = 0,
        solve_tol: float = 1e-6,
        bounces: int | None = None,
    ) -> Row:
        fine, parent, K, E0, kt = self.kernel(k, kmethod, ff_tol, samples, seed)
        refl = torch.full((fine.num_facets,), self.r, dtype=DTYPE)

        def run() -> torch.Tensor:
            E = self.solve(K, refl, E0, bounces=bounces, tol=solve_tol)
            return self.scene.average_to_parent(E.reshape(fine.num_facets, -1), parent, fine)

        Ec, st = timed(run)
        rmse, mx = rel_errors(Ec.detach().numpy().reshape(-1), self.ref["irradiance"])
        return Row(self.name, method, setting, fine.num_facets, kt, st, rmse, mx, {"k": k})


# ---------------------------------------------------------------------------------------------- Mitsuba
def mitsuba_rows(
    name: str, ref: dict, spps: Sequence[int], sampler: str = "independent", seed: int = 1000
) -> list[Row]:
    spec = ref["settings"]
    scene = mr.build_scene(spec)
    t0 = time.perf_counter()
    m = mr.MitsubaReference(
        scene, spec["reflectance"], mr.make_light(spec["light"]), sampler=sampler, origin=spec.get("mitsuba_origin")
    )
    build = time.perf_counter() - t0
    cold = m.render(16, seed=seed - 1)  # compiles the kernels (cached on disk afterwards)
    rows = []
    for i, spp in enumerate(spps):
        r = m.render_warm(spp, seed=seed + i)
        rmse, mx = rel_errors(r.irradiance, ref["irradiance"])
        rows.append(
            Row(
                name,
                f"Mitsuba 3 ({sampler})",
                f"{r.spp} spp",
                m.num_facets,
                build,
                r.seconds,
                rmse,
                mx,
                {"spp": r.spp, "first_render_s": cold.seconds},
            )
        )
    return rows


def time_at_error(points: Sequence[tuple[float, float]], target: float) -> float:
    """Time to reach ``target`` error on a measured (error, time) curve: log-log interpolation inside it,
    Monte Carlo's ``time ∝ error⁻²`` below its smallest error; NaN above its largest (where fixed costs rule)."""
    pts = sorted((e, t) for e, t in points if e > 0 and t > 0)
    if not pts or not target > 0:
        return math.nan
    # keep it monotone: more time never gives more error on a Monte Carlo curve
    mono: list[tuple[float, float]] = []
    for e, t in pts:
        if not mono or t < mono[-1][1]:
            mono.append((e, t))
    le = np.log([p[0] for p in mono])
    lt = np.log([p[1] for p in mono])
    x = math.log(target)
    if x <= le[0]:
        return float(math.exp(lt[0] - 2.0 * (x - le[0])))
    if x > le[-1]:
        return math.nan
    return float(math.exp(np.interp(x, le, lt)))


# ---------------------------------------------------------------------------------------------- spectral
SPECTRAL_NAME = "vgroove45_spectral_nikon"


def spectral_setup(divisions: int = 10) -> dict:
    """V-groove 45°: plate A ColorChecker "orange", plate B "white 9.5", D65 sun along the bisector."""
    wl = ti.spectral.wavelengths(dtype=DTYPE)
    scene = ti.scenes.v_groove(45.0, divisions=divisions, dtype=DTYPE)
    plate = scene.material.numpy()
    ra = ti.spectral.reflectance("orange", wl)
    rb = ti.spectral.reflectance("white", wl)
    refl = torch.stack([ra, rb])[torch.as_tensor(plate)]  # [F, L]
    spd = ti.spectral.illuminant("D65", wl) / 100.0
    C = ti.spectral.camera_sensitivities("Nikon 5100 (NPL)", wl)  # [3, L]
    half = math.radians(22.5)
    d = [-math.cos(half), 0.0, -math.sin(half)]
    return {"wl": wl, "scene": scene, "refl": refl, "spd": spd, "C": C, "direction": d, "origin": [0.0, 0.045, 0.0]}


def spectral_mitsuba(s: dict, sampler: str = "independent") -> mr.MitsubaReference:
    refl = s["refl"].numpy()
    # camera RGB of radiance: Σ_λ C_k(λ) r(λ) E(λ) / π Δλ  ->  weights C_k r / π per facet
    w = s["C"].numpy()[None, :, :] * refl[:, None, :] / math.pi
    light = mr.Directional(tuple(s["direction"]), tuple(s["spd"].numpy()))
    return mr.MitsubaReference(
        s["scene"],
        refl,
        light,
        variant="llvm_ad_spectral",
        wavelengths=s["wl"].numpy(),
        weights=w,
        sampler=sampler,
        origin=s["origin"],
    )


def make_spectral_reference(target: float = 2.5e-4, max_paths: float = 4e8) -> dict:
    """The spectral reference: Mitsuba ``llvm_ad_spectral``, camera RGB per facet (see spectral_setup)."""
    import mitsuba as mi

    s = spectral_setup()
    m = spectral_mitsuba(s, sampler="multijitter")
    F = m.num_facets
    t0 = time.perf_counter()
    # two independent renders, each a pilot extended by more paths (pooled: mean and its standard error)
    a, b, _ = mr.pilot_and_extend(m.render, F, target=target, max_paths=max_paths)
    e = 0.5 * (a.irradiance + b.irradiance)
    half = 0.5 * np.abs(a.irradiance - b.irradiance)
    rms = float(np.sqrt(np.mean((half / e) ** 2)))
    mr.REFERENCE_DIR.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        mr.REFERENCE_DIR / f"{SPECTRAL_NAME}.npz",
        irradiance=e.astype(np.float32),
        noise=(np.full_like(e, rms) * e).astype(np.float32),
        render_a=a.irradiance.astype(np.float32),
        render_b=b.irradiance.astype(np.float32),
    )
    settings = {
        "name": SPECTRAL_NAME,
        "scene": "v_groove(45, size=(0.09, 0.06), divisions=10); plate_a ColorChecker 'orange', plate_b 'white 9.5'",
        "light": {"type": "directional", "direction": s["direction"], "spd": "D65 / 100 (W/m^2/nm)"},
        "wavelengths": "400-700 nm, 10 nm (31)",
        "quantity": "camera RGB of the facet's radiance, sum_l C_k(l) r(l) E(l) / pi * 10 nm, Nikon 5100 (NPL)",
        "shape": "[F, 3]",
        "renderer": f"Mitsuba {mi.__version__} llvm_ad_spectral, path max_depth=-1, irradiancemeter estimator "
        "batched; 4 wavelengths per path drawn at the grid's nodes (stratified), so the discrete-wavelength "
        "problem is solved exactly; sampler multijitter",
        "spp_per_render": int(a.spp),
        "spp_total": int(a.spp + b.spp),
        "rel_noise_rms": rms,
        "seconds": time.perf_counter() - t0,
    }
    (mr.REFERENCE_DIR / f"{SPECTRAL_NAME}.json").write_text(json.dumps(settings, indent=1) + "\n")
    return settings


def spectral_rows(ref: dict, spps: Sequence[int], ks: Sequence[int], with_mitsuba: bool) -> list[Row]:
    s = spectral_setup()
    scene = s["scene"]
    target = ref["irradiance"]  # [F, 3]
    rows = []
    for k in ks:

        def kern(k: int = k) -> tuple:
            fine, parent = scene.subdivide(k)
            K = ti.form_factors(fine, progress=False)
            E0 = ti.lights.directional(fine, torch.tensor(s["direction"], dtype=DTYPE), s["spd"])
            return fine, parent, K, E0

        (fine, parent, K, E0), kt = timed(kern, budget=10.0, reps=2)
        refl = s["refl"][parent]

        def run(fine: Any = fine, parent: Any = parent, K: Any = K, E0: Any = E0, refl: Any = refl) -> torch.Tensor:
            E = solve(K, refl, E0)
            rgb = ti.spectral_to_rgb(refl * E / math.pi, s["C"], s["wl"])  # [F_fine, 3]
            return scene.average_to_parent(rgb, parent, fine)

        rgb, st = timed(run)
        rmse, mx = rel_errors(rgb.numpy(), target)
        rows.append(Row(SPECTRAL_NAME, "ours", f"k={k} (31 λ)", fine.num_facets, kt, st, rmse, mx, {"k": k}))
    if with_mitsuba:
        t0 = time.perf_counter()
        m = spectral_mitsuba(s)
        build = time.perf_counter() - t0
        m.render(16, seed=5)
        for i, spp in enumerate(spps):
            r = m.render_warm(spp, seed=2000 + i)
            rmse, mx = rel_errors(r.irradiance, target)
            rows.append(
                Row(
                    SPECTRAL_NAME,
                    "Mitsuba 3 (independent)",
                    f"{spp} spp",
                    m.num_facets,
                    build,
                    r.seconds,
                    rmse,
                    mx,
                    {"spp": spp},
                )
            )
    return rows


# ---------------------------------------------------------------------------------------------- scaling
def _scaling_point(args: argparse.Namespace) -> None:
    """Child process: one scaling measurement, printed as JSON (peak RSS is per process)."""
    torch.set_grad_enabled(False)
    d = torch.tensor([-math.cos(math.radians(22.5)), 0.0, -math.sin(math.radians(22.5))], dtype=DTYPE)
    # warm-up: first calls load the ray tracer and set up caches
    w = ti.scenes.v_groove(45.0, divisions=2, dtype=DTYPE)
    solve(
        ti.form_factors(w, progress=False),
        torch.full((8,), 0.5, dtype=DTYPE),
        ti.lights.directional(w, d, torch.ones(3, dtype=DTYPE)),
    )
    n = args.n
    scene = ti.scenes.v_groove(45.0, size=(0.09, 0.06), divisions=n, dtype=DTYPE)
    L, B = args.wavelengths, args.batch
    base = status_mb("VmRSS")
    t0 = time.perf_counter()
    K = ti.form_factors(scene, progress=False)
    E0 = ti.lights.directional(scene, d, torch.ones(L, dtype=DTYPE))
    t1 = time.perf_counter()
    peak_kernel = status_mb("VmHWM")
    g = torch.Generator().manual_seed(0)
    refl = 0.2 + 0.7 * torch.rand(B, scene.num_facets, L, generator=g, dtype=DTYPE)
    (E, st) = timed(lambda: solve(K, refl, E0.expand(B, -1, -1)))
    peak = status_mb("VmHWM")
    rec = {
        "facets": scene.num_facets,
        "wavelengths": L,
        "batch": B,
        "kernel_s": t1 - t0,
        "solve_s": st,
        "layout": "sparse" if K.is_sparse else "dense",
        "nnz": K.nnz,
        "rss_base_mb": base,
        "rss_peak_kernel_mb": peak_kernel,
        "rss_peak_mb": peak,
        "finite": bool(torch.isfinite(E).all()),
    }
    print(json.dumps(rec))


#: Peak memory of one scaling point per F² (bytes), measured: 5.8 GB at 10,082 facets, 21.3 GB at 20,000.
BYTES_PER_PAIR = 55.0


def scaling(points: Sequence[tuple[int, int, int]], timeout: float) -> list[dict]:
    out = []
    for n, L, B in points:
        args = ["_scaling_point", "--n", str(n), "--wavelengths", str(L), "--batch", str(B)]
        t0 = time.perf_counter()
        need = BYTES_PER_PAIR * (2 * n * n) ** 2
        if need > 0.95 * mem_available():
            rec = {"error": f"skipped: needs ~{need / 1e9:.0f} GB, {mem_available() / 1e9:.0f} GB available"}
            rec.update(n=n, request={"facets": 2 * n * n, "wavelengths": L, "batch": B}, wall_s=0.0)
            print("  scaling", rec, flush=True)
            out.append(rec)
            continue
        rec = run_worker("benchmarks.speed_vs_error", args, timeout=timeout)
        rec.update(n=n, request={"facets": 2 * n * n, "wavelengths": L, "batch": B}, wall_s=time.perf_counter() - t0)
        print("  scaling", rec, flush=True)
        out.append(rec)
    return out


def fit_exponent(x: Sequence[float], y: Sequence[float]) -> float:
    x, y = np.log(np.asarray(x, float)), np.log(np.asarray(y, float))
    if len(x) < 2:
        return math.nan
    return float(np.polyfit(x, y, 1)[0])


# ---------------------------------------------------------------------------------------------- report
def table(rows: list[Row], mitsuba: list[tuple[float, float]], noise: float) -> list[str]:
    out = [
        "| method | setting | facets | rel. RMSE | max error | kernel | solve | total | Mitsuba at equal error "
        "| ratio |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        is_mitsuba = r.method.startswith("Mitsuba")
        e = debias(r.rmse, noise)
        tm = time_at_error(mitsuba, e) if mitsuba and not is_mitsuba else math.nan
        ratio = f"{tm / r.total_s:.2g}×" if math.isfinite(tm) else "–"
        if mitsuba and not is_mitsuba and e == 0:
            tm, ratio = math.nan, "below ref. noise"
        out.append(
            f"| {r.method} | {r.setting} | {r.facets} | {fmt_e(r.rmse)} | {fmt_e(r.max_err)} | {fmt_t(r.kernel_s)} | "
            f"{fmt_t(r.solve_s)} | {fmt_t(r.total_s)} | {fmt_t(tm)} | {ratio} |"
        )
    return out


def plot(scene_rows: dict[str, list[Row]], path: Path, title: str) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    names = list(scene_rows)
    ncol = min(3, len(names))
    nrow = math.ceil(len(names) / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.2 * ncol, 3.4 * nrow), squeeze=False)
    styles = {
        "ours": "o-",
        "ours (quadrature tol)": "s",
        "ours (solver tol)": "D",
        "ours n-bounce": "^",
        "MC kernel": "v-",
        "Mitsuba 3 (independent)": "x-",
        "Mitsuba 3 (multijitter)": "+--",
    }
    for ax, name in zip(axes.ravel(), names, strict=False):
        by: dict[str, list[Row]] = {}
        for r in scene_rows[name]:
            by.setdefault(r.method, []).append(r)
        for method, rs in by.items():
            ax.loglog(
                [r.total_s for r in rs], [max(r.rmse, 1e-6) for r in rs], styles.get(method, "o"), label=method, ms=4
            )
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("time (s)", fontsize=8)
        ax.set_ylabel("per-facet rel. RMSE", fontsize=8)
        ax.grid(True, which="both", alpha=0.3)
        ax.tick_params(labelsize=7)
    for ax in axes.ravel()[len(names) :]:
        ax.axis("off")
    axes.ravel()[0].legend(fontsize=6)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=80 if len(names) <= 6 else 60)
    plt.close(fig)


def _parse_time(t: str) -> float:
    v, unit = t.split()
    return float(v) * (1e-3 if unit == "ms" else 1.0)


def rows_from_markdown(path: Path) -> dict[str, list[Row]]:
    """The result rows of a written report (for re-plotting without re-running)."""
    out: dict[str, list[Row]] = {}
    name = None
    for line in path.read_text().splitlines():
        if line.startswith("## "):
            name = SPECTRAL_NAME if line.startswith("## Spectral") else line[3:].strip()
            continue
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if name is None or len(cells) != 10 or not cells[3].endswith("%") or cells[0] == "method":
            continue
        try:
            row = Row(
                name,
                cells[0],
                cells[1],
                int(cells[2]),
                _parse_time(cells[5]),
                _parse_time(cells[6]),
                float(cells[3].split()[0]) / 100,
                float(cells[4].split()[0]) / 100,
            )
        except ValueError:
            continue
        out.setdefault(name, []).append(row)
    return out


def plot_scaling(recs: list[dict], path: Path) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    ok = [r for r in recs if "facets" in r and r["wavelengths"] == 31 and r["batch"] == 1]
    if not ok:
        return
    fig, ax = plt.subplots(1, 2, figsize=(8.4, 3.2))
    f = [r["facets"] for r in ok]
    ax[0].loglog(f, [r["kernel_s"] for r in ok], "o-", label="form factors + direct light")
    ax[0].loglog(f, [r["solve_s"] for r in ok], "s-", label="solve (31 λ)")
    ax[0].set_xlabel("facets")
    ax[0].set_ylabel("time (s)")
    ax[0].legend(fontsize=7)
    ax[1].loglog(f, [r["rss_peak_mb"] for r in ok], "o-")
    ax[1].set_xlabel("facets")
    ax[1].set_ylabel("peak RSS (MB)")
    for a in ax:
        a.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


# ---------------------------------------------------------------------------------------------- main
def configs(quick: bool) -> dict:
    if quick:
        return {
            "scenes": ["vgroove30_sun_r9", "vgroove30_sun_r2", "box_corner_sun_r9", "w_shape_sun_r9", "cornell_sky_r9"],
            "refine": [1, 2, 3],
            "max_facets": 1500,
            "ff_tol": [1e-3],
            "solve_tol": [1e-3],
            "bounces": [2, 3, 4],
            "mc_samples": [1000, 10000],
            "mitsuba_spp": [256, 1024, 4096, 16384],
            "mitsuba_samplers": ["independent"],
            "spectral_k": [1],
            "spectral_spp": [256, 1024, 4096],
            "scaling": [(7, 31, 1), (10, 31, 1), (16, 31, 1), (23, 31, 1), (20, 1, 1), (20, 81, 1), (20, 31, 8)],
            "scaling_timeout": 120.0,
        }
    return {
        "scenes": None,  # all references
        "refine": [1, 2, 3, 4],
        "max_facets": 4000,
        "ff_tol": [1e-3, 1e-4],
        "solve_tol": [1e-2, 1e-3, 1e-9],
        "bounces": [2, 3, 4],
        "mc_samples": [1000, 10000, 100000],
        "mitsuba_spp": [64, 256, 1024, 4096, 16384, 65536, 262144],
        "mitsuba_samplers": ["independent", "multijitter"],
        "spectral_k": [1, 2],
        "spectral_spp": [256, 1024, 4096, 16384, 65536],
        "scaling": [
            (7, 31, 1),
            (10, 31, 1),
            (16, 31, 1),
            (23, 31, 1),
            (32, 31, 1),
            (50, 31, 1),
            (71, 31, 1),
            (100, 31, 1),
            (20, 1, 1),
            (20, 8, 1),
            (20, 81, 1),
            (20, 301, 1),
            (20, 31, 4),
            (20, 31, 16),
            (20, 31, 64),
        ],
        "scaling_timeout": 1800.0,
    }


def run_scene(name: str, cfg: dict, with_mitsuba: bool) -> tuple[list[Row], list[Row], float]:
    ref = mr.load_reference(name)
    noise = float(ref["settings"]["rel_noise_rms"])
    o = Ours(name, ref)
    rows: list[Row] = []
    ks = [k for k in cfg["refine"] if k == 1 or o.scene.num_facets * k * k <= cfg["max_facets"]]
    for k in ks:
        rows.append(o.row("ours", f"k={k}", k))
        print("  ", rows[-1], flush=True)
    for tol in cfg["ff_tol"]:
        for k in ks[:2]:
            rows.append(o.row("ours (quadrature tol)", f"k={k}, form-factor tol {tol:g}", k, ff_tol=tol))
    k_mid = ks[min(1, len(ks) - 1)]
    for tol in cfg["solve_tol"]:
        rows.append(o.row("ours (solver tol)", f"k={k_mid}, solve tol {tol:g}", k_mid, solve_tol=tol))
    k_top = ks[-1]
    for b in cfg["bounces"]:
        rows.append(o.row("ours n-bounce", f"k={k_top}, {b} bounces", k_top, bounces=b))
    for n in cfg["mc_samples"]:
        rows.append(o.row("MC kernel", f"k=1, {n} rays/facet", 1, kmethod="monte_carlo", samples=n))
        print("  ", rows[-1], flush=True)
    mits: list[Row] = []
    if with_mitsuba:
        for sampler in cfg["mitsuba_samplers"]:
            mits += mitsuba_rows(name, ref, cfg["mitsuba_spp"], sampler=sampler)
            print("  ", mits[-1], flush=True)
    return rows, mits, noise


def main(argv: Sequence[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("cmd", nargs="?", default="run", choices=["run", "_scaling_point", "spectral-reference", "replot"])
    p.add_argument("--quick", action="store_true", help="a subset that runs in under 10 minutes")
    p.add_argument("--no-mitsuba", action="store_true")
    p.add_argument("--no-scaling", action="store_true")
    p.add_argument("--no-spectral", action="store_true")
    p.add_argument("--scenes", nargs="*", default=None)
    p.add_argument("--threads", type=int, default=None, help="threads for torch and Mitsuba (default: all cores)")
    p.add_argument("--n", type=int, default=10)
    p.add_argument("--wavelengths", type=int, default=31)
    p.add_argument("--batch", type=int, default=1)
    a = p.parse_args(argv)
    if a.cmd == "_scaling_point":
        _scaling_point(a)
        return
    if a.cmd == "spectral-reference":
        print(make_spectral_reference())
        return
    if a.cmd == "replot":
        suffix = "_quick" if a.quick else ""
        rows = rows_from_markdown(RESULTS / f"speed_vs_error{suffix}.md")
        spectral = {SPECTRAL_NAME: rows.pop(SPECTRAL_NAME, [])}
        plot(rows, RESULTS / f"speed_vs_error{suffix}.png", "time against per-facet error")
        if spectral[SPECTRAL_NAME]:
            plot(spectral, RESULTS / f"speed_vs_error_spectral{suffix}.png", "spectral (camera RGB)")
        return
    t_start = time.perf_counter()
    cfg = configs(a.quick)
    names = a.scenes or cfg["scenes"] or [n for n in mr.reference_names() if n != SPECTRAL_NAME]
    names = [n for n in names if (mr.REFERENCE_DIR / f"{n}.npz").exists()]
    with_mitsuba = not a.no_mitsuba and mr.available("llvm_ad_mono")
    if a.threads:
        torch.set_num_threads(a.threads)
        if with_mitsuba:
            import drjit

            drjit.set_thread_count(a.threads)
    torch.set_grad_enabled(False)
    # warm-up (imports, first-call overheads)
    w = ti.scenes.v_groove(45.0, divisions=2, dtype=DTYPE)
    E0w = ti.lights.directional(w, torch.tensor([0.0, 0.0, -1.0], dtype=DTYPE), torch.ones(1, dtype=DTYPE))
    solve(ti.form_factors(w), torch.full((w.num_facets,), 0.5, dtype=DTYPE), E0w)

    suffix = "_quick" if a.quick else ""
    md: list[str] = [
        f"# Speed against error{' (quick)' if a.quick else ''}",
        "",
        f"Generated by `python -m benchmarks.speed_vs_error{' --quick' if a.quick else ''}` on "
        f"{platform.node() or 'this machine'}"
        f" ({os.cpu_count()} CPUs, torch {torch.__version__}, {torch.get_num_threads()} threads"
        f"{', Mitsuba ' + _mitsuba_version() if with_mitsuba else ', Mitsuba not installed'}).",
        "",
        "Errors are per-facet relative errors of the irradiance against the cached Mitsuba reference of each scene",
        "(`benchmarks/references/`, noise level in each table's heading). *RMSE* and *max* are as measured (they "
        "include",
        "the reference's noise); the equal-error column takes the reference noise out in quadrature from both",
        "curves before reading Mitsuba's time off its time-against-error curve (log-log interpolation, `t ∝ e⁻²`",
        "beyond its ends). Ours: `k` is the `Scene.subdivide(k)` refinement (solved on `k²` times more facets,",
        "area-averaged back); *kernel* = form factors + direct light, *solve* = `solve` + averaging; default",
        "form-factor tol 1e-6 and solver tol 1e-6. Mitsuba: *kernel* = scene build, *solve* = rendering (kernels",
        "compiled beforehand). Our timings are the fastest of up to 3 runs (kernels: 2) while the runs take",
        "under 6 s (10 s) in all; a render under 2 s is repeated and timed the second time. Both use all cores",
        f"(load average at the start: {loadavg()}; the machine may be shared, which inflates single timings;",
        f"OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY')}: spinning OpenMP threads make torch 5-50x slower on"
        " a busy CPU).",
        "",
    ]
    intro = md
    md = []
    all_rows: dict[str, list[Row]] = {}
    headline: list[str] = [
        "| scene | facets | ref. noise | 1 %: ours vs Mitsuba | 0.3 %: ours vs Mitsuba | 0.1 %: ours vs Mitsuba "
        "| 2-bounce error | 3-bounce error | ∞, finest k |",
        "|---|---:|---:|---|---|---|---:|---:|---:|",
    ]
    for name in names:
        print(name, flush=True)
        rows, mits, noise = run_scene(name, cfg, with_mitsuba)
        all_rows[name] = rows + mits
        curve = [(debias(r.rmse, noise), r.total_s) for r in mits]
        ref = mr.load_reference(name)
        st = ref["settings"]
        md += [
            f"## {name}",
            "",
            f"{st['builder']}({', '.join(f'{k}={v}' for k, v in st['kwargs'].items())}), "
            f"reflectance {st['reflectance']}, "
            f"{st['light']['type']} light; {st['num_facets']} facets; reference {st['spp_total']:,} paths per facet, "
            f"relative noise {100 * noise:.3f} % RMS.",
            "",
        ]
        md += [*table(rows + mits, curve, noise), ""]
        inf_rows = [r for r in rows if r.method in ("ours", "ours (quadrature tol)", "ours (solver tol)")]
        cells = [name, str(st["num_facets"]), fmt_e(noise)]
        for target in (0.01, 0.003, 0.001):
            ok = [r.total_s for r in inf_rows if debias(r.rmse, noise) <= target]
            ours_t = min(ok) if ok else math.nan
            mit_t = time_at_error(curve, target) if curve else math.nan
            mit_s = fmt_t(mit_t)
            if not math.isfinite(mit_t) and curve:  # the target lies above Mitsuba's measured curve
                mit_t = min((t for e, t in curve if e <= target), default=math.nan)
                mit_s = f"≤ {fmt_t(mit_t)}"
            cell = f"{fmt_t(ours_t) if ok else 'not reached'} vs {mit_s}"
            if ok and math.isfinite(mit_t):
                q = mit_t / ours_t
                cell += f" (ours {q:.2g}× faster)" if q >= 1 else f" (Mitsuba {1 / q:.2g}× faster)"
            cells.append(cell)
        for b in (2, 3):
            nb = [r for r in rows if r.method == "ours n-bounce" and r.setting.endswith(f"{b} bounces")]
            cells.append(f"{fmt_e(nb[0].rmse)} (max {fmt_e(nb[0].max_err)})" if nb else "–")
        top = [r for r in rows if r.method == "ours"][-1]
        cells.append(f"{fmt_e(top.rmse)} ({top.setting})")
        headline.append("| " + " | ".join(cells) + " |")
    plot(all_rows, RESULTS / f"speed_vs_error{suffix}.png", "time against per-facet error")
    head = [
        "## Headline",
        "",
        "Time to reach a per-facet relative RMSE of 1 %, 0.3 %, 0.1 % (reference noise taken out of both): ours is",
        "the cheapest infinite-bounce setting that reaches it, Mitsuba's is read off its time-against-error curve.",
        "n-bounce errors (RMSE, max) are at the finest refinement, next to the infinite-bounce error there.",
        "",
        *headline,
        "",
        f"![time against error](speed_vs_error{suffix}.png)",
        "",
    ]
    md = intro + head + md

    if not a.no_spectral:
        sref_path = mr.REFERENCE_DIR / f"{SPECTRAL_NAME}.npz"
        if sref_path.exists():
            print("spectral", flush=True)
            sref = {
                "irradiance": np.load(sref_path)["irradiance"].astype(np.float64),
                "settings": json.loads((mr.REFERENCE_DIR / f"{SPECTRAL_NAME}.json").read_text()),
            }
            srows = spectral_rows(
                sref, cfg["spectral_spp"], cfg["spectral_k"], with_mitsuba and mr.available("llvm_ad_spectral")
            )
            snoise = float(sref["settings"]["rel_noise_rms"])
            scurve = [(debias(r.rmse, snoise), r.total_s) for r in srows if r.method.startswith("Mitsuba")]
            md += [
                "## Spectral: 31 wavelengths to camera RGB",
                "",
                f"{sref['settings']['scene']}; {sref['settings']['quantity']}. "
                f"Reference: {sref['settings']['renderer']},"
                f" {sref['settings']['spp_total']:,} paths per facet, relative noise {100 * snoise:.3f} % RMS "
                "(errors are per facet and channel).",
                "",
            ]
            md += [*table(srows, scurve, snoise), ""]
            plot({SPECTRAL_NAME: srows}, RESULTS / f"speed_vs_error_spectral{suffix}.png", "spectral (camera RGB)")
            md += [f"![spectral](speed_vs_error_spectral{suffix}.png)", ""]
        else:
            md += ["## Spectral", "",
                   "(no spectral reference: run `python -m benchmarks.speed_vs_error spectral-reference`)", ""]

    if not a.no_scaling:
        print("scaling", flush=True)
        recs = scaling(cfg["scaling"], cfg["scaling_timeout"])
        md += [
            "## Scaling",
            "",
            "V-groove 45° (9 × 6 cm) with `divisions=n` (2n² facets), sun, random reflectance in [0.2, 0.9];"
            " each point in its own process (peak RSS is that process's maximum resident set, torch and its"
            " libraries included).",
            "",
            "| facets | wavelengths | batch | layout | nnz | kernel | solve | peak RSS | RSS before |",
            "|---:|---:|---:|---|---:|---:|---:|---:|---:|",
        ]
        for r in recs:
            if "facets" in r:
                md.append(
                    f"| {r['facets']} | {r['wavelengths']} | {r['batch']} | {r['layout']} | {r['nnz']:,} | "
                    f"{fmt_t(r['kernel_s'])} | {fmt_t(r['solve_s'])} | {r['rss_peak_mb']:.0f} MB | "
                    f"{r['rss_base_mb']:.0f} MB |"
                )
            else:
                q = r["request"]
                md.append(f"| {q['facets']} | {q['wavelengths']} | {q['batch']} | – | – | {r['error']} | – | – | – |")
        fac = [r for r in recs if "facets" in r and r["wavelengths"] == 31 and r["batch"] == 1 and r["facets"] >= 500]
        if len(fac) >= 2:
            nf = [r["facets"] for r in fac]
            ek, es, em = (fit_exponent(nf, [r[key] for r in fac]) for key in ("kernel_s", "solve_s", "rss_peak_mb"))
            md += [
                "",
                f"Fitted exponents (facets ≥ 500): kernel time ∝ F^{ek:.2f}, solve time ∝ F^{es:.2f}, "
                f"peak RSS ∝ F^{em:.2f}.",
            ]
        for key, label in (("wavelengths", "wavelengths"), ("batch", "batch size")):
            pts = [
                r
                for r in recs
                if "facets" in r
                and r["facets"] == 800
                and (r["batch"] == 1 if key == "wavelengths" else r["wavelengths"] == 31)
            ]
            if len(pts) >= 2:
                md.append(
                    f"Solve time against {label} (800 facets): ∝ {label}^"
                    f"{fit_exponent([r[key] for r in pts], [r['solve_s'] for r in pts]):.2f}."
                )
        plot_scaling(recs, RESULTS / f"speed_vs_error_scaling{suffix}.png")
        md += ["", f"![scaling](speed_vs_error_scaling{suffix}.png)", ""]

    md += [f"Total benchmark time: {time.perf_counter() - t_start:.0f} s; load average at the end: {loadavg()}.", ""]
    write_lines(RESULTS / f"speed_vs_error{suffix}.md", md)


def _mitsuba_version() -> str:
    try:
        import mitsuba

        return mitsuba.__version__
    except ImportError:
        return "?"


if __name__ == "__main__":
    main()
