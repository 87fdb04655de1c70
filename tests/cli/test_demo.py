"""The demo: its table against an independent recomputation (dense numpy solve and Neumann sums), its figures
against their content."""

import json

import numpy as np
import pytest
import torch

import torch_interreflect as ti
from torch_interreflect import spectral
from torch_interreflect.cli import main
from torch_interreflect.cli.demo import ILLUMINANTS, PATCHES, DemoConfig, run_demo
from torch_interreflect.training.storage import read_png

DIV = 4


@pytest.fixture(scope="module")
def demo(tmp_path_factory: pytest.TempPathFactory):
    out = tmp_path_factory.mktemp("demo")
    return out, run_demo(out, DemoConfig(angles=(45.0,), divisions=DIV), progress=False)


def _recompute(patch: str, illuminant: str, bounces: int) -> tuple[np.ndarray, np.ndarray]:
    """Relative RMS difference (%) of the ``bounces``-bounce camera RGB against ∞: hinge column, all facets."""
    cfg = DemoConfig()
    scene = ti.scenes.v_groove(45.0, size=cfg.size, divisions=DIV, dtype=torch.float64)
    F = ti.form_factors(scene).to_dense().numpy()  # [n, n]
    wl = spectral.wavelengths(dtype=torch.float64)
    r = spectral.reflectance(PATCHES[patch], wl).numpy()  # [L]
    e0 = spectral.illuminant(ILLUMINANTS[illuminant], wl).numpy()
    e0 = e0 / e0.max()
    n = F.shape[0]
    E_inf = np.stack([np.linalg.solve(np.eye(n) - F * r[k], np.full(n, e0[k])) for k in range(r.size)], -1)
    E_n, term = np.zeros_like(E_inf), np.broadcast_to(e0, E_inf.shape).copy()
    for _ in range(bounces):  # E_n = Σ_{k < n} (F R)^k E0
        E_n += term
        term = F @ (r * term)
    cam = ti.Camera.from_colour(cfg.camera, wl)
    rgb_inf, rgb_n = (cam(torch.from_numpy(r * E / np.pi)).numpy() for E in (E_inf, E_n))  # [n, 3]
    hinge = (torch.hypot(scene.centroids[:, 0], scene.centroids[:, 2]) < cfg.size[1] / DIV).numpy()  # first column

    def rel(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return 100 * np.sqrt(((a - b) ** 2).mean(0)) / np.sqrt((b**2).mean(0))

    assert hinge.sum() == 2 * DIV
    return rel(rgb_n[hinge], rgb_inf[hinge]), rel(rgb_n, rgb_inf)


@pytest.mark.parametrize("patch, illuminant, bounces", [("red", "D50", 2), ("grey", "incandescent (A)", 3),
                                                        ("cyan", "D50", 4)])
def test_demo_table_equals_an_independent_recomputation(demo, patch, illuminant, bounces) -> None:
    out, _ = demo
    v = json.loads((out / "results.json").read_text())["table"]["45"][illuminant][patch][str(bounces)]
    hinge, overall = _recompute(patch, illuminant, bounces)  # agree to 2.3e-7 at most (measured)
    np.testing.assert_allclose(v["hinge_column_%"], hinge, rtol=7e-7)
    np.testing.assert_allclose(v["overall_%"], overall, rtol=7e-7)
    np.testing.assert_allclose(v["per_column_%"][0], hinge, rtol=7e-7)
    table = (out / "table9.md").read_text()
    assert f"| {patch} | {bounces} | " + " | ".join(f"{x:.2f}" for x in (*hinge, *overall)) + " |" in table


def test_demo_numbers_make_sense_and_figures_hold_pictures(demo) -> None:
    out, res = demo
    table = res["table"]["45"]["D50"]
    for patch, by_b in table.items():
        worst = {b: max(v["hinge_column_%"]) for b, v in by_b.items()}
        overall = {b: max(v["overall_%"]) for b, v in by_b.items()}
        # more bounces, closer to infinity; the hinge column is where the error lives
        assert worst["2"] > worst["3"] > worst["4"] > 0, patch
        assert worst["2"] > overall["2"], patch
        cols = [max(c) for c in by_b["2"]["per_column_%"]]
        assert cols == sorted(cols, reverse=True), patch  # the error falls away from the hinge
    # a bright patch needs the extra bounces more than a dark one
    assert max(table["red"]["2"]["hinge_column_%"]) > max(table["blue"]["2"]["hinge_column_%"])
    for name in ("form_factors.png", "images_45deg_D50.png", "images_45deg_A.png", "difference_vs_distance.png"):
        img = read_png(out / name)
        assert img.ndim == 3 and img.shape[2] == 3 and min(img.shape[:2]) > 200, name
        ink = (img < 200).any(-1).mean()  # share of pixels that are not (near) white
        assert 0.03 < ink < 0.9, (name, ink)
        assert len(np.unique(img.reshape(-1, 3), axis=0)) > 50, name  # colour maps and patches, not a blank page
    assert res["timings"]["45"]["facets"] == 2 * DIV * DIV


def test_cli_demo(tmp_path, capsys) -> None:
    assert main(["demo", "--out", str(tmp_path), "--angles", "60", "--divisions", "3", "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "V-groove 60°: 18 facets" in out and "table9.md" in out and "Done in" in out
    row = next(line for line in out.splitlines() if line.startswith("red "))
    first = json.loads((tmp_path / "results.json").read_text())["table"]["60"]["D50"]["red"]["2"]
    assert f"{max(first['hinge_column_%']):9.2f} / {max(first['overall_%']):8.2f}" in row
