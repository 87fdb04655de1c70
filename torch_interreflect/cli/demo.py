"""The paper's V-groove experiment on built-in scenes: n-bounce against infinite-bounce camera RGB.

Deeb et al. (2017), §6: two 9 cm × 6 cm plates (10 × 10 facets each) at 45° and 60°, ColorChecker patches,
a homogeneous light, a camera with known sensitivities; images for 2, 3, 4 and ∞ bounces, a table like their
Table 9 (difference of the n-bounce RGB against ∞ on the column of facets nearest the hinge and overall, per
channel) and a plot like their Fig. 12 (that difference against the column's distance from the hinge).

Run it with ``interreflect demo --out DIR`` (or ``make demo``).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch
from tqdm.auto import tqdm

from .. import lights, spectral
from ..camera.rendering import render_view
from ..camera.sensor import Camera
from ..camera.view import View
from ..formfactors.quadrature import form_factors
from ..geometry import scenes
from ..solver.api import radiance, solve

__all__ = ["DemoConfig", "run_demo"]

PATCHES = {"red": "red", "orange": "orange", "blue": "blue", "cyan": "cyan", "grey": "neutral 6.5 (.44 D)"}
ILLUMINANTS = {"D50": "D50", "incandescent (A)": "A"}
BOUNCES: tuple[int | None, ...] = (2, 3, 4, None)


@dataclass
class DemoConfig:
    """Settings of the demo (the paper's by default)."""

    angles: tuple[float, ...] = (45.0, 60.0)
    size: tuple[float, float] = (0.09, 0.06)
    divisions: int = 10
    camera: str = "Nikon 5100 (NPL)"
    patches: dict[str, str] = field(default_factory=lambda: dict(PATCHES))
    illuminants: dict[str, str] = field(default_factory=lambda: dict(ILLUMINANTS))
    dtype: torch.dtype = torch.float64


def _bounce_name(b: int | None) -> str:
    return "inf" if b is None else str(b)


def _rel_diff(rgb_n: torch.Tensor, rgb_inf: torch.Tensor) -> torch.Tensor:
    """Relative RMS difference per channel (%), over the facets on dim -2."""
    return 100.0 * ((rgb_n - rgb_inf) ** 2).mean(-2).sqrt() / (rgb_inf**2).mean(-2).sqrt()


def run_demo(out: str | Path, config: DemoConfig | None = None, *, progress: bool = True) -> dict:
    """Run the experiment, write images, tables and plots to ``out``, and return the numbers.

    Args:
        out: Output folder (created).
        config: Settings (defaults reproduce the paper's design).
        progress: Show a progress bar.

    Returns:
        A dict with the Table-9-like numbers, keyed by angle, illuminant, patch and bounces.
    """
    cfg = config or DemoConfig()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    wl = spectral.wavelengths(dtype=cfg.dtype)
    cam = Camera.from_colour(cfg.camera, wl).to(cfg.dtype)
    names = list(cfg.patches)
    refl = torch.stack([spectral.reflectance(cfg.patches[n], wl) for n in names])  # [P, L]
    illum = torch.stack([spectral.illuminant(cfg.illuminants[n], wl) for n in cfg.illuminants])  # [I, L]
    illum = illum / illum.max(dim=-1, keepdim=True).values
    n = cfg.divisions
    results: dict = {"config": {"angles": list(cfg.angles), "size_m": list(cfg.size), "divisions": n,
                                "camera": cfg.camera, "patches": cfg.patches, "illuminants": cfg.illuminants},
                     "table": {}, "timings": {}}
    written: list[Path] = []
    images: dict = {}
    steps = len(cfg.angles) * len(BOUNCES)
    bar = tqdm(total=steps, desc="demo", unit="solve", disable=not progress)
    for angle in cfg.angles:
        scene = scenes.v_groove(angle, size=cfg.size, divisions=n, dtype=cfg.dtype)
        t = time.perf_counter()
        K = form_factors(scene)
        t_kernel = time.perf_counter() - t
        if angle == cfg.angles[0]:
            written.append(_plot_matrix(K.to_dense(), scene, out / "form_factors.png", angle))
            written.append(_plot_view(scene, K, refl[0], illum[0], cam, cfg, out / f"view_{angle:g}deg.png"))
        F = scene.num_facets
        # every facet of both plates has the patch's reflectance; homogeneous direct light (the paper's indoor
        # configuration): E0 = illuminant on every facet
        r = refl[:, None, :].expand(len(names), F, -1)  # [P, F, L]
        E0 = lights.uniform(scene, illum)[:, None]  # [I, 1, F, L]
        rgb = {}
        t = time.perf_counter()
        for b in BOUNCES:
            E = solve(K, r, E0, bounces=b)  # [I, P, F, L]
            rgb[b] = cam(radiance(E, r))  # [I, P, F, 3]
            bar.update(1)
        t_solve = time.perf_counter() - t
        results["timings"][f"{angle:g}"] = {"kernel_s": t_kernel, "solve_s": t_solve, "facets": F,
                                             "pairs": K.info.get("pairs")}
        # facets: plate p, column c (0 at the hinge), row r -> index p*n*n + c*n + r
        grid = {b: v.reshape(*v.shape[:2], 2, n, n, 3) for b, v in rgb.items()}  # [I, P, plate, col, row, 3]
        for ii, iname in enumerate(cfg.illuminants):
            for pi, pname in enumerate(names):
                ref = grid[None][ii, pi]
                for b in BOUNCES[:-1]:
                    g = grid[b][ii, pi]
                    hinge = _rel_diff(g[:, 0].reshape(-1, 3), ref[:, 0].reshape(-1, 3))
                    overall = _rel_diff(g.reshape(-1, 3), ref.reshape(-1, 3))
                    per_col = torch.stack([_rel_diff(g[:, c].reshape(-1, 3), ref[:, c].reshape(-1, 3))
                                           for c in range(n)])  # [n, 3]
                    results["table"].setdefault(f"{angle:g}", {}).setdefault(iname, {}).setdefault(pname, {})[
                        _bounce_name(b)] = {"hinge_column_%": hinge.tolist(), "overall_%": overall.tolist(),
                                            "per_column_%": per_col.tolist()}
        images[angle] = {b: grid[b] for b in BOUNCES}
    bar.close()
    # white balance for display only: divide by the camera RGB of each illuminant on a perfect white
    white = cam((illum / torch.pi)[:, None, :])[:, 0]  # [I, 3]
    for angle in cfg.angles:
        for ii, iname in enumerate(cfg.illuminants):
            path = out / f"images_{angle:g}deg_{cfg.illuminants[iname]}.png"
            wb = white[ii] / white[ii].max()
            balanced = {b: v / wb for b, v in images[angle].items()}
            written.append(_plot_images(balanced, ii, names, path,
                                        f"V-groove {angle:g}°, {iname}, {cfg.camera}, white-balanced"))
    written.append(_plot_fig12(results, cfg, names, out / "difference_vs_distance.png"))
    md = _table_markdown(results, cfg, names)
    (out / "table9.md").write_text(md)
    written.append(out / "table9.md")
    results["timings"]["total_s"] = time.perf_counter() - t_start
    (out / "results.json").write_text(json.dumps(results, indent=1))
    written.append(out / "results.json")
    results["written"] = [str(p) for p in written]
    return results


def _table_markdown(results: dict, cfg: DemoConfig, names: list[str]) -> str:
    col_w = cfg.size[1] / cfg.divisions * 1000
    lines = [
        "# Relative RMS difference of n-bounce camera RGB against infinite bounces (%)",
        "",
        f"V-grooves of two {cfg.size[0] * 100:g} cm × {cfg.size[1] * 100:g} cm plates, {cfg.divisions}×"
        f"{cfg.divisions} facets each; homogeneous light; camera {cfg.camera}. 'hinge' is the column of facets "
        f"nearest the shared edge (first {col_w:g} mm of each plate), 'all' every facet.",
        "",
    ]
    for angle, by_ill in results["table"].items():
        for iname, by_patch in by_ill.items():
            lines += [f"## {angle}°, {iname}", "",
                      "| patch | bounces | hinge R | hinge G | hinge B | all R | all G | all B |",
                      "|---|---|---|---|---|---|---|---|"]
            for p in names:
                for b, v in by_patch[p].items():
                    h, a = v["hinge_column_%"], v["overall_%"]
                    lines.append(f"| {p} | {b} | " + " | ".join(f"{x:.2f}" for x in (*h, *a)) + " |")
            lines.append("")
    return "\n".join(lines)


def _plt():
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError("the demo's figures need matplotlib: pip install 'torch_interreflect[plot]'") from exc
    return plt


def _display(rgb: torch.Tensor, scale: float) -> torch.Tensor:
    """Linear camera RGB → values for display (scaled, clipped, sRGB-like gamma)."""
    x = (rgb / scale).clamp(0, 1)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


def _plot_images(grid: dict, ii: int, names: list[str], path: Path, title: str) -> Path:
    plt = _plt()
    fig, axes = plt.subplots(len(names), len(BOUNCES), figsize=(2.2 * len(BOUNCES), 1.3 * len(names)),
                             squeeze=False)
    for pi, pname in enumerate(names):
        scale = float(grid[None][ii, pi].max())
        for bi, b in enumerate(BOUNCES):
            g = grid[b][ii, pi]  # [plate, col, row, 3]
            # unfold the groove: plate B mirrored to the left of the hinge, plate A to the right
            img = torch.cat([g[1].flip(0), g[0]], dim=0).transpose(0, 1)  # [row, col, 3]
            axes[pi, bi].imshow(_display(img, scale).numpy(), interpolation="nearest")
            axes[pi, bi].set_xticks([])
            axes[pi, bi].set_yticks([])
            if pi == 0:
                axes[pi, bi].set_title(f"{_bounce_name(b)} bounces" if b else "∞ bounces", fontsize=9)
            if bi == 0:
                axes[pi, bi].set_ylabel(pname, fontsize=9)
    fig.suptitle(title + " (plates unfolded at the hinge)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _plot_fig12(results: dict, cfg: DemoConfig, names: list[str], path: Path) -> Path:
    plt = _plt()
    angle = next(iter(results["table"]))
    iname = next(iter(cfg.illuminants))
    col_w = cfg.size[1] / cfg.divisions * 1000
    dist = [(c + 0.5) * col_w for c in range(cfg.divisions)]
    fig, axes = plt.subplots(1, len(names), figsize=(2.6 * len(names), 2.6), sharey=True, squeeze=False)
    for pi, pname in enumerate(names):
        ax = axes[0, pi]
        for b, v in results["table"][angle][iname][pname].items():
            worst = [max(row) for row in v["per_column_%"]]
            ax.plot(dist, worst, marker="x" if b == "2" else "o", ms=3, label=f"{b} bounces")
        ax.set_title(pname, fontsize=9)
        ax.set_xlabel("distance from hinge (mm)", fontsize=8)
        ax.set_yscale("log")
        ax.grid(alpha=0.3)
    axes[0, 0].set_ylabel("RGB difference to ∞ (%), worst channel", fontsize=8)
    axes[0, -1].legend(fontsize=7)
    fig.suptitle(f"V-groove {angle}°, {iname}: where the n-bounce models go wrong (cf. Deeb et al. Fig. 12)",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _plot_view(scene, K, r: torch.Tensor, S: torch.Tensor, cam: Camera, cfg: DemoConfig, path: Path) -> Path:
    """The groove through a pinhole camera looking into it: flat shading (one colour per facet) against the final
    gather per pixel, for ∞ and 2 bounces (the first patch under the first illuminant, homogeneous light)."""
    length, width = cfg.size
    view = View(eye=(2.3 * width, length / 2, width), target=(0.3 * width, length / 2, 0.15 * width), fov_deg=50.0,
                height=72, width=96)
    rr = r.expand(scene.num_facets, -1)
    shots = {}
    for b, shading in ((None, "flat"), (None, "gather"), (2, "gather")):
        E = solve(K, rr, S.expand(scene.num_facets, -1), bounces=b)
        shots[(b, shading)] = render_view(scene, rr, E, S, cam, view, "uniform", shading=shading)  # [3, H, W]
    scale = float(shots[(None, "gather")].max())
    plt = _plt()
    fig, axes = plt.subplots(1, 3, figsize=(9, 2.6))
    titles = {(None, "flat"): "∞ bounces, flat per facet", (None, "gather"): "∞ bounces, gathered per pixel",
              (2, "gather"): "2 bounces, gathered per pixel"}
    for ax, (key, img) in zip(axes, shots.items(), strict=True):
        ax.imshow(_display(img.permute(1, 2, 0), scale).numpy())
        ax.set_title(titles[key], fontsize=9)
        ax.set_axis_off()
    fig.suptitle(f"V-groove {cfg.angles[0]:g}°, {next(iter(cfg.patches))} patch, {cfg.camera} (not white-balanced)",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _plot_matrix(F: torch.Tensor, scene, path: Path, angle: float) -> Path:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(4.2, 3.6))
    v = F.double().clamp_min(1e-8).log10().numpy()
    im = ax.imshow(v, cmap="magma", vmin=-6, vmax=0, interpolation="nearest")
    fig.colorbar(im, ax=ax, label="log10 F_ij")
    ax.set_title(f"Form factors, V-groove {angle:g}° ({scene.num_facets} facets)", fontsize=9)
    ax.set_xlabel("j (receiving)", fontsize=8)
    ax.set_ylabel("i (emitting)", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
