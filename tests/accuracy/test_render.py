"""render(accuracy=...) on the constant basis (``basis="constant"``: refinement, extrapolation, sparsification,
bounces, wavelength reduction): error estimate against finer solutions, layout and power, gradients and the
errors/warnings for unreachable targets. The quadratic basis (the default where it applies) has its own tests in
``test_render_quadratic.py``."""

from __future__ import annotations

import dataclasses
import math
import warnings

import pytest
import torch

import torch_interreflect as ti
from torch_interreflect.accuracy import plan as _plan
from torch_interreflect.errors import AccuracyWarning, ShapeError, ValueRangeError

D = torch.float64
ONE = torch.ones(1, dtype=D)
WL = torch.tensor([550.0], dtype=D)


def render(*args, **kwargs):
    """``ti.render`` on the constant basis, whose refinement and settings these tests are about."""
    kwargs.setdefault("basis", "constant")
    return ti.render(*args, **kwargs)


def plan(*args, **kwargs):
    kwargs.setdefault("basis", "constant")
    return _plan(*args, **kwargs)


def _grey(scene: ti.Scene, r: float, dtype: torch.dtype = D) -> torch.Tensor:
    return torch.full((scene.num_facets,), r, dtype=dtype)


@pytest.fixture(scope="module")
def groove() -> ti.Scene:
    return ti.scenes.v_groove(45.0, size=(1.0, 1.0), divisions=2, dtype=D)


@pytest.fixture(scope="module")
def groove_reference(groove: ti.Scene) -> torch.Tensor:
    """Uniform refinement k = 6 and 12, extrapolated (first order): E ≈ 2 E_12 − E_6 under uniform light."""
    out = []
    for k in (6, 12):
        fine, parent = groove.subdivide(k)
        E = ti.solve(ti.form_factors(fine), _grey(fine, 0.8), torch.ones(fine.num_facets, 1, dtype=D))
        out.append(groove.average_to_parent(E, parent, fine)[:, 0])
    return 2 * out[1] - out[0]


@pytest.fixture(scope="module")
def groove_fitted_reference(groove: ti.Scene) -> torch.Tensor:
    """Uniform refinement k = 4, 8, 16 under uniform light, extrapolated with the order fitted on the three (1.56;
    within 4e-5 of the same from k = 6, 12, 24)."""
    out = []
    for k in (4, 8, 16):
        fine, parent = groove.subdivide(k)
        E = ti.solve(ti.form_factors(fine), _grey(fine, 0.8), torch.ones(fine.num_facets, 1, dtype=D))
        out.append(groove.average_to_parent(E, parent, fine)[:, 0])
    order = math.log2(_rel_rms(out[1], out[0]) / _rel_rms(out[2], out[1]))
    return out[2] + (out[2] - out[1]) / (2**order - 1)


def _rel_rms(x: torch.Tensor, ref: torch.Tensor) -> float:
    return float(((x - ref) / ref).square().mean().sqrt())


@pytest.mark.parametrize("accuracy", [3e-2, 1e-2])
def test_error_stays_below_the_request_and_the_estimate_is_honest(groove, groove_reference, accuracy):
    out = render(groove, _grey(groove, 0.8), "uniform", ONE, wavelengths=WL, accuracy=accuracy)
    actual = _rel_rms(out.irradiance[:, 0], groove_reference)
    rep = out.report
    assert rep.reached and rep.estimated <= accuracy
    assert actual <= accuracy
    # the estimate is of the right size: not below half the actual error, not 20x above it
    assert rep.estimated >= 0.5 * actual
    assert rep.estimated <= 20 * actual + 1e-4
    # it refined, and refined the facets at the hinge (indices of the hinge row) at least as much as the rest
    assert rep.leaves > groove.num_facets
    hinge = (groove.centroids[:, 0].abs() < 0.3) & (groove.centroids[:, 2].abs() < 0.3)
    assert int(rep.leaves_per_facet[hinge].min()) >= int(rep.leaves_per_facet[~hinge].max())


def test_tighter_accuracy_does_more_work_and_gets_closer(groove, groove_reference):
    a = render(groove, _grey(groove, 0.8), "uniform", ONE, wavelengths=WL, accuracy=3e-2)
    b = render(groove, _grey(groove, 0.8), "uniform", ONE, wavelengths=WL, accuracy=5e-3)
    assert b.report.leaves > a.report.leaves
    assert _rel_rms(b.irradiance[:, 0], groove_reference) < _rel_rms(a.irradiance[:, 0], groove_reference)


def test_closed_box_is_exact_at_any_refinement():
    # uniform E0 and reflectance in a closed box: E = E0 / (1 - r) exactly, whatever the discretisation
    box = ti.scenes.closed_box(divisions=2, dtype=D)
    out = render(box, _grey(box, 0.7), "uniform", ONE, wavelengths=WL, accuracy=1e-3)
    # what is left is the form factors' closure error (rows sum to 1 + 5.9e-7 at the planned quadrature tolerance,
    # amplified by 1 / (1 - r)): measured 1.38e-6
    torch.testing.assert_close(out.irradiance, torch.full_like(out.irradiance, 1 / 0.3), rtol=2e-6, atol=0)
    assert out.report.parts["discretisation"] < 1e-6
    assert out.report.iterations == 0  # the a-priori estimate (corners gathered) sees no error: no refinement
    assert out.report.leaves == box.num_facets


def test_refinement_keeps_the_layout_and_the_total_power(groove):
    r = torch.linspace(0.3, 0.9, groove.num_facets, dtype=D)
    p = plan(groove, r, [-0.9, 0.1, -0.3], ONE, wavelengths=WL, accuracy=1e-2)  # lights both plates
    assert p.report.extrapolated and p.coarse is not None and p.report.iterations >= 1
    p = dataclasses.replace(p, method="dense", bounces=None)
    level = dataclasses.replace(p, coarse=None, extrapolation=None)  # the last level alone
    out = level.apply(r, ONE)
    assert out.irradiance.shape == (groove.num_facets, 1)
    # leaves tile the user's facets: areas add up per facet
    leaf_area = torch.zeros(groove.num_facets, dtype=D).index_add(0, p.leaf_user, p.leaves.areas)
    torch.testing.assert_close(leaf_area, groove.areas, rtol=1e-12, atol=0)
    # the power the user facets receive is the power the leaves receive
    E_leaf = ti.solve(p.form_factors, r[p.leaf_user], p.light_factor[:, None], method="dense")
    torch.testing.assert_close(
        (groove.areas * out.irradiance[:, 0]).sum(), (p.leaves.areas * E_leaf[:, 0]).sum(), rtol=1e-9, atol=0
    )
    # the plan's output is the Richardson extrapolation x + c (x - x_coarse), x_coarse every facet one split back
    low = dataclasses.replace(p.coarse, method="dense", bounces=None).apply(r, ONE).irradiance
    c = p.extrapolation
    assert bool(((c >= 0) & (c <= 2 / 3 + 1e-12)).all()) and bool((c > 0).any())
    torch.testing.assert_close(p.apply(r, ONE).irradiance, out.irradiance + c[:, None] * (out.irradiance - low),
                               rtol=1e-12, atol=0)


@pytest.mark.parametrize(("accuracy", "ratio"), [(3e-2, 0.25), (1e-2, 0.01)])
def test_extrapolation_lowers_the_error_and_the_estimate_covers_it(groove, groove_fitted_reference, accuracy, ratio):
    """The extrapolated output against the last level alone (measured: 0.28 % vs 1.69 % at 3e-2, where six of the
    eight facets are split, and 0.0083 % vs 1.56 % at 1e-2, all split; one refinement each)."""
    r = _grey(groove, 0.8)
    p = plan(groove, r, "uniform", ONE, wavelengths=WL, accuracy=accuracy)
    assert p.report.extrapolated and p.report.reached
    extrapolated = _rel_rms(p.apply(r, ONE).irradiance[:, 0], groove_fitted_reference)
    last = dataclasses.replace(p, coarse=None, extrapolation=None).apply(r, ONE).irradiance[:, 0]
    assert extrapolated <= ratio * _rel_rms(last, groove_fitted_reference)
    assert extrapolated <= p.report.estimated


def test_without_extrapolation_the_last_level_is_returned(groove, groove_fitted_reference):
    r = _grey(groove, 0.8)
    p = plan(groove, r, "uniform", ONE, wavelengths=WL, accuracy=1e-2, extrapolate=False)
    assert not p.report.extrapolated and p.coarse is None and p.extrapolation is None and p.report.iterations >= 1
    actual = _rel_rms(p.apply(r, ONE).irradiance[:, 0], groove_fitted_reference)
    assert actual <= p.report.estimated <= 3 * actual  # measured 0.64 % and 0.70 %


def test_sparsified_kernel_stays_within_its_bound():
    scene = ti.scenes.closed_box(divisions=4, dtype=D)
    K = ti.form_factors(scene)
    r = torch.full((scene.num_facets,), 0.8, dtype=D)
    e0 = torch.rand(scene.num_facets, 2, dtype=D, generator=torch.Generator().manual_seed(0))
    E = ti.solve(K, r, e0, method="dense")
    for mass in (1e-3, 1e-2):
        Ks = K.sparsify(mass)
        assert Ks.nnz < K.nnz and Ks.info["dropped_row_mass"] <= mass
        AF = scene.areas[:, None] * Ks.to_dense()
        torch.testing.assert_close(AF, AF.T, rtol=1e-12, atol=1e-15)  # reciprocity kept: cg still applies
        Es = ti.solve(Ks, r, e0, method="cg", tol=1e-12)
        rho = 0.8 * float(K.row_sums().max())
        bound = mass * 0.8 * E.abs().max() / (1 - rho)
        err = (Es - E).abs().max()
        assert err <= bound
        assert err > 0  # something was dropped and it shows


def test_dark_scene_uses_the_bounce_series_within_its_bound(groove):
    out = render(groove, _grey(groove, 0.2), "uniform", ONE, wavelengths=WL, accuracy=1e-2)
    rep = out.report
    assert rep.method == "series" and rep.bounces is not None and rep.bounces >= 2
    # the series on the same leaves against the exact solve of the same leaves
    p = plan(groove, _grey(groove, 0.2), "uniform", ONE, wavelengths=WL, accuracy=1e-2)
    exact = ti.solve(p.form_factors, _grey(p.leaves, 0.2), p.light_factor[:, None], method="dense")
    series = ti.solve(p.form_factors, _grey(p.leaves, 0.2), p.light_factor[:, None], bounces=rep.bounces)
    rel = ((series - exact) / exact).abs().max()
    assert rel <= rep.parts["solver"]
    assert rep.parts["solver"] <= 0.05 * 1e-2 + 1e-15


def test_bright_scene_uses_conjugate_gradients(groove):
    rep = render(groove, _grey(groove, 0.95), "uniform", ONE, wavelengths=WL, accuracy=1e-2).report
    assert rep.method == "cg" and rep.bounces is None


def test_camera_rgb_on_fewer_wavelengths():
    scene = ti.scenes.v_groove(60.0, size=(1.0, 1.0), divisions=2, dtype=D)
    wl = ti.spectral.wavelengths(dtype=D)
    cam = ti.Camera.from_colour("Nikon 5100 (NPL)", wl)
    patches = ti.spectral.colorchecker(wl)[0][[0, 6, 12, 18]].to(D)  # 4 spectra, one per pair of facets
    r = patches.repeat_interleave(2, 0)
    p = plan(scene, r, "uniform", "D65", cam, accuracy=2e-2)
    rep = p.report
    assert rep.wavelengths.numel() < 31
    got = p.apply(r, "D65", cam).rgb
    full = dataclasses.replace(p, nodes=torch.arange(31)).apply(r, "D65", cam).rgb
    err = float(((got - full) / full).square().mean().sqrt())
    assert err <= 0.2 * 2e-2 + rep.parts["solver"]
    assert err <= 2 * rep.wavelength_error + 1e-3


def test_gradients_reach_reflectance_and_illuminant(groove):
    r = torch.full((groove.num_facets,), 0.6, dtype=D)
    p = plan(groove, r, "uniform", ONE, wavelengths=WL, accuracy=5e-2)
    p = dataclasses.replace(p, method="dense", bounces=None)  # exact solve: checks the gather / average plumbing
    s = torch.full((1,), 2.0, dtype=D, requires_grad=True)
    rr = r.clone().requires_grad_(True)
    torch.autograd.gradcheck(lambda a, b: p.apply(a, b).irradiance, (rr, s))


def test_float32_matches_float64(groove):
    a = render(groove, _grey(groove, 0.8), "uniform", ONE, wavelengths=WL, accuracy=2e-2).irradiance
    g32 = groove.to(torch.float32)
    b = render(g32, _grey(g32, 0.8, torch.float32), "uniform", ONE.float(), wavelengths=WL.float(), accuracy=2e-2)
    assert b.irradiance.dtype == torch.float32 and b.report.reached
    # both are within 2e-2 of the truth, so within 4e-2 of each other (refinement choices may differ)
    assert _rel_rms(b.irradiance.double()[:, 0], a[:, 0]) <= 4e-2


def test_accuracy_below_what_the_dtype_resolves_is_an_error(groove):
    g32 = groove.to(torch.float32)
    with pytest.raises(ValueRangeError, match="float32"):
        render(g32, _grey(g32, 0.5, torch.float32), accuracy=1e-6)
    for bad in (0.0, -1e-2, 0.7, math.nan, True):
        with pytest.raises(ValueRangeError):
            render(groove, _grey(groove, 0.5), accuracy=bad)


def test_unreachable_accuracy_warns_and_says_so(groove):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = render(groove, _grey(groove, 0.9), "uniform", ONE, wavelengths=WL, accuracy=1e-4, max_facets=200)
    assert any(issubclass(w.category, AccuracyWarning) and "max_facets=200" in str(w.message) for w in caught)
    assert not out.report.reached and out.report.estimated > 1e-4
    assert out.report.leaves <= 200


def test_bad_shapes(groove):
    with pytest.raises(ShapeError, match="reflectance"):
        render(groove, torch.full((5,), 0.5, dtype=D), accuracy=1e-2)
    with pytest.raises(ShapeError, match="illuminant"):
        render(groove, _grey(groove, 0.5), "uniform", torch.ones(3, dtype=D), wavelengths=WL, accuracy=1e-2)
    with pytest.raises(ValueRangeError, match=r"\[0, 1\]"):
        render(groove, _grey(groove, 1.5), accuracy=1e-2)
    with pytest.raises(TypeError):
        render("groove", _grey(groove, 0.5))  # type: ignore[arg-type]


def test_layer_with_accuracy_keeps_the_scene_facets_and_meets_the_target():
    scene = ti.scenes.v_groove(45.0, size=(1.0, 1.0), divisions=2, dtype=D)
    wl = ti.spectral.wavelengths(dtype=D)
    layer = ti.layers.Interreflection(scene, wl, accuracy=2e-2).to(D)
    assert layer.accuracy_report.reached and layer.matrix.shape[0] > scene.num_facets
    r = torch.full((2, 8, 31), 0.8, dtype=D, requires_grad=True)
    d65 = ti.spectral.illuminant("D65", wl).to(D)
    rgb = layer(r, d65)
    assert rgb.shape == (2, 8, 3)
    cam = ti.Camera.from_colour("Nikon 5100 (NPL)", wl).to(D)
    ref = render(scene, r[0].detach(), "uniform", d65, cam, accuracy=3e-3).rgb
    assert _rel_rms(rgb[0].detach(), ref) <= 2e-2 + 3e-3
    rgb.sum().backward()
    assert r.grad is not None and bool(torch.isfinite(r.grad).all()) and float(r.grad.abs().min()) > 0
    assert "leaves" in repr(layer)


def test_occluded_scene_under_a_sky_warns_or_bounds_the_error():
    """Issue 13 item 12: the Cornell box under a sky (r = 0.2) against the stored converged Mitsuba reference. The
    sky's ray-cast open part has a Monte Carlo error that refinement does not lower; it is measured and reported
    (0.59 % since the directions are drawn afresh per point: before, one shared set biased whole walls by up to 3 %),
    and whenever the actual error exceeds the request an AccuracyWarning is issued."""
    import json
    from pathlib import Path

    import numpy as np

    refs = Path(__file__).resolve().parents[2] / "benchmarks" / "references"
    spec = json.loads((refs / "cornell_sky_r2.json").read_text())
    reference = torch.from_numpy(np.load(refs / "cornell_sky_r2.npz")["irradiance"].astype(np.float64))
    scene = ti.scenes.cornell_box(**spec["kwargs"], dtype=D)
    level = torch.full((1,), spec["light"]["radiance"], dtype=D)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = render(
            scene, _grey(scene, spec["reflectance"]), "sky", level, wavelengths=WL, accuracy=1e-2, max_facets=240
        )
    warned = any(issubclass(w.category, AccuracyWarning) for w in caught)
    actual = _rel_rms(out.irradiance[:, 0], reference)
    rep = out.report
    assert 3e-3 <= rep.parts["light"] <= 1.2e-2  # measured 0.59 % (16 vs 24 directions per axis)
    assert rep.estimated >= actual  # measured 10.4 % against 7.1 %
    if actual > 1e-2:
        assert warned and not rep.reached


def test_render_with_a_view_returns_the_gathered_image():
    """``render(view=...)`` shades the refined leaves per pixel: in a closed box under uniform light with uniform
    reflectance every point has ``E = E0 / (1 − r)``, so every pixel's radiance is ``r E / π`` exactly."""
    scene = ti.scenes.closed_box(1.0, divisions=2, dtype=torch.float64)
    wl = torch.tensor([500.0, 600.0], dtype=torch.float64)
    view = ti.View((0.5, 0.2, 0.5), (0.5, 0.8, 0.4), up=(0.0, 0.0, 1.0), fov_deg=60.0, height=8, width=10)
    r = 0.6
    out = render(scene, torch.full((scene.num_facets,), r, dtype=torch.float64), light="uniform",
                    illuminant=torch.tensor([1.0, 2.0], dtype=torch.float64), wavelengths=wl, accuracy=2e-2,
                    view=view, progress=False)
    assert out.image is not None and out.image.shape == (2, 8, 10)
    expected = torch.tensor([1.0, 2.0], dtype=torch.float64) * r / (1 - r) / math.pi
    # the plan solves to its own tolerance (here the facets' radiance is 1.4e-5 off): the image may not be worse
    facet_err = float(((out.radiance - expected) / expected).abs().max())
    image_err = float(((out.image - expected[:, None, None]) / expected[:, None, None]).abs().max())
    assert facet_err < out.report.estimated and image_err <= facet_err + 1e-7  # measured 1.21e-5 vs 1.36e-5
    flat = render(scene, torch.full((scene.num_facets,), r, dtype=torch.float64), light="uniform",
                     illuminant=torch.tensor([1.0, 2.0], dtype=torch.float64), wavelengths=wl, accuracy=2e-2,
                     view=view, shading="flat", progress=False)
    flat_err = float(((flat.image - expected[:, None, None]) / expected[:, None, None]).abs().max())
    assert flat_err <= 3 * facet_err  # flat paints each solved leaf's own value: measured 3.0e-5 (2.2x)


def _uniform_reference(scene: ti.Scene, r: float, light, ks=(6, 12)) -> torch.Tensor:
    """First-order extrapolation ``2 E_12 − E_6`` of uniform refinements (the light a direction or 'uniform')."""
    out = []
    for k in ks:
        fine, parent = scene.subdivide(k)
        K = ti.form_factors(fine)
        g = ti.lights.light_geometry(fine, K, light)
        E = ti.solve(K, _grey(fine, r), g[:, None])
        out.append(scene.average_to_parent(E, parent, fine)[:, 0])
    return 2 * out[1] - out[0]


@pytest.mark.parametrize("r, light", [(0.2, "uniform"), (0.8, "uniform"), (0.5, (-0.9, 0.1, -0.3)), (0.8, "sky")])
def test_a_priori_estimate_bounds_the_error_of_one_solve(groove, r, light):
    """``accuracy.apriori.estimate`` (the corners gathered, the sources of the error from their covariance with the
    point form factors) against the actual error of the solve on the user's facets: estimated / actual RMS
    2.41 / 1.90 / 2.19 / 1.63 (the sky: the corners' light from their open hemisphere), every facet below its
    estimate (the closest at 0.63 of it)."""
    from torch_interreflect.accuracy import apriori

    light = light if isinstance(light, str) else torch.tensor(light, dtype=D)
    K = ti.form_factors(groove)
    g = ti.lights.light_geometry(groove, K, light)
    refl = _grey(groove, r)[:, None]
    h = ti.solve(K, refl, g[:, None], method="dense")
    est = apriori.estimate(groove, K, refl, g, h, light)
    ref = _uniform_reference(groove, r, light)
    actual = ((h[:, 0] - ref) / ref).abs()
    assert est.shape == (groove.num_facets,) and est.dtype == torch.float64
    rms_actual, rms_est = float(actual.square().mean().sqrt()), float(est.square().mean().sqrt())
    assert rms_actual <= rms_est <= 3.5 * rms_actual
    assert bool((actual <= est).all())


def test_a_priori_estimate_does_not_depend_on_the_facet_order():
    """A wall standing on the line between two floor facets, in sun: the floor's corners at the wall's foot are not
    shared across it (each side has its own light), so the estimate follows the facets when they are reordered."""
    from torch_interreflect.accuracy import apriori

    a = [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]
    b = [[1, 0, 0], [2, 0, 0], [2, 1, 0], [1, 1, 0]]
    c = [[2, 0, 0], [3, 0, 0], [3, 1, 0], [2, 1, 0]]
    wall = [[1, 1, 0], [1, 0, 0], [1, 0, 1], [1, 1, 1]]  # x = 1, facing -x
    sun = torch.tensor([1.0, 0.0, -2.0], dtype=D)
    est = []
    for order in ([0, 1, 2, 3], [1, 0, 3, 2]):
        scene = ti.Scene.from_polygons(torch.tensor([[a, b, c, wall][i] for i in order], dtype=D))
        K = ti.form_factors(scene)
        g = ti.lights.light_geometry(scene, K, sun)
        r = torch.full((4, 1), 0.8, dtype=D)
        h = ti.solve(K, r, g[:, None], method="dense")
        e = apriori.estimate(scene, K, r, g, h, sun)
        est.append(torch.empty_like(e).index_copy_(0, torch.tensor(order), e))
    torch.testing.assert_close(est[0], est[1], rtol=1e-9, atol=0)
    assert float(est[0][0]) > 0 and float(est[0][3]) > 0


def test_a_priori_estimate_in_small_blocks(groove, monkeypatch):
    """The covariances are summed in blocks of source facets (``COV_BLOCK`` entries): one facet per block, its rows
    gathered from the sparse factors (not made dense), gives the same estimate, for two columns of reflectance."""
    from torch_interreflect.accuracy import apriori

    K = ti.form_factors(groove)
    light = torch.tensor((-0.9, 0.1, -0.3), dtype=D)
    g = ti.lights.light_geometry(groove, K, light)
    refl = torch.stack([_grey(groove, 0.8), torch.linspace(0.3, 0.9, groove.num_facets, dtype=D)], -1)
    h = ti.solve(K, refl, g[:, None].expand(-1, 2), method="dense")
    whole = apriori.estimate(groove, K, refl, g, h, light)
    monkeypatch.setattr(apriori, "COV_BLOCK", 1)
    torch.testing.assert_close(apriori.estimate(groove, K, refl, g, h, light), whole, rtol=1e-12, atol=0)
    assert bool((whole > 0).all())


def test_a_priori_estimate_sums_the_series_on_dark_scenes(groove, monkeypatch):
    """Where ``ρ = r_max · max row sum`` is at most ``NEUMANN_RHO`` the estimate's solve sums the Neumann series to
    its tolerance (1e-3) instead of factoring: the same estimate within it (r = 0.2, a sun; measured 2.5e-5)."""
    from torch_interreflect.accuracy import apriori

    K = ti.form_factors(groove)
    light = torch.tensor((-0.9, 0.1, -0.3), dtype=D)
    g = ti.lights.light_geometry(groove, K, light)
    refl = _grey(groove, 0.2)[:, None]
    h = ti.solve(K, refl, g[:, None], method="dense")
    series = apriori.estimate(groove, K, refl, g, h, light)
    monkeypatch.setattr(apriori, "NEUMANN_RHO", -1.0)  # the solver's own choice (a factorisation here)
    factored = apriori.estimate(groove, K, refl, g, h, light)
    torch.testing.assert_close(series, factored, rtol=1e-3, atol=0)
    assert not torch.equal(series, factored)  # the series was summed, not the factorisation repeated


def test_kept_leaves_keep_their_sky_rays():
    """After a split, a kept leaf whose sky value is a count of escaping rays keeps the value it had; every other
    leaf gets the value of a full cast."""
    from torch_interreflect.accuracy.kernel import leaf_kernel
    from torch_interreflect.accuracy.leaves import Leaves, light_factor, split

    box = ti.scenes.cornell_box(1, light=False, dtype=D)
    leaves = Leaves(box, torch.arange(box.num_facets))
    K0 = leaf_kernel(box, 1e-4)
    g0 = light_factor("sky", box, K0, leaves.user, box.num_facets)
    sel = torch.zeros(box.num_facets, dtype=torch.bool)
    sel[::3] = True
    new = split(leaves, sel)
    K1 = leaf_kernel(new.scene, 1e-4, K0, new.kept)
    full = light_factor("sky", new.scene, K1, new.user, box.num_facets)
    reused = light_factor("sky", new.scene, K1, new.user, box.num_facets, g0[new.kept])
    m = new.kept.numel()
    occ = K1.info["occluded_facets"][:m]
    assert bool(occ.any())
    torch.testing.assert_close(reused[:m][occ], g0[new.kept][occ], rtol=0, atol=0)
    assert not torch.equal(full[:m][occ], g0[new.kept][occ])  # a full cast draws other rays (new indices)
    torch.testing.assert_close(reused[:m][~occ], full[:m][~occ], rtol=0, atol=0)
    torch.testing.assert_close(reused[m:], full[m:], rtol=0, atol=0)


def test_dark_scene_is_not_refined_when_one_solve_meets_the_target(groove):
    """r = 0.2: the a-priori estimate of the solve on the user's facets already meets 1e-2, so no refinement."""
    ref = _uniform_reference(groove, 0.2, "uniform")
    out = render(groove, _grey(groove, 0.2), "uniform", ONE, wavelengths=WL, accuracy=1e-2)
    rep = out.report
    assert rep.iterations == 0 and rep.leaves == groove.num_facets and rep.reached
    actual = _rel_rms(out.irradiance[:, 0], ref)
    assert actual <= rep.estimated <= 1e-2


def test_refinement_steps_reuse_the_kernel_of_unchanged_leaves():
    """``accuracy.kernel.leaf_kernel`` copies the kept × kept block and integrates only the pairs with a new leaf:
    equal to the kernel computed from scratch (measured max difference 1e-18 on a V-groove)."""
    from torch_interreflect.accuracy.kernel import leaf_kernel
    from torch_interreflect.accuracy.leaves import Leaves, split

    scene = ti.scenes.v_groove(30.0, divisions=4, dtype=D)
    K0 = ti.form_factors(scene, quadrature_tol=1e-4)
    sel = torch.zeros(scene.num_facets, dtype=torch.bool)
    sel[::3] = True
    leaves = split(Leaves(scene, torch.arange(scene.num_facets)), sel)
    assert leaves.kept is not None and leaves.kept.numel() == int((~sel).sum())
    K = leaf_kernel(leaves.scene, 1e-4, K0, leaves.kept)
    assert K.info["reused_entries"] > 0
    fresh = ti.form_factors(leaves.scene, quadrature_tol=1e-4).to_dense()
    torch.testing.assert_close(K.to_dense(), fresh, rtol=0, atol=1e-15)


def test_a_wavelength_without_light_does_not_break_the_float32_estimate(groove):
    """An illuminant that is zero at one wavelength: that column is zero everywhere, and the relative change must
    count it as 0 (in float32 its floor once underflowed to 0, the estimate became NaN and refinement ran to the
    facet cap while the report said reached)."""
    g32 = groove.to(torch.float32)
    wl = torch.tensor([450.0, 550.0, 650.0])
    out = render(g32, _grey(g32, 0.8, torch.float32), "uniform", torch.tensor([0.0, 1.0, 1.0]), wavelengths=wl,
                    accuracy=1e-2)
    rep = out.report
    assert math.isfinite(rep.parts["discretisation"]) and rep.reached and rep.leaves <= 100  # measured 80
    assert bool((out.irradiance[:, 0] == 0).all()) and bool((out.irradiance[:, 1:] > 0).all())


def test_the_coarse_level_holds_every_facet_one_split_back(groove):
    """After several partial refinements the coarse level tiles every user facet with its leaves from before its own
    last split: a quarter of its leaves where it was split (every leaf of a split facet is split in four), all of
    them where it never was; and extrapolation applies to every split facet, not only to the last step's."""
    r = _grey(groove, 0.8)
    p = plan(groove, r, [-0.9, 0.1, -0.3], ONE, wavelengths=WL, accuracy=2e-3)
    assert p.report.iterations >= 3 and p.coarse is not None
    F = groove.num_facets
    fine = torch.bincount(p.leaf_user, minlength=F)
    coarse = torch.bincount(p.coarse.leaf_user, minlength=F)
    split = fine > 1
    assert bool(split.any()) and bool((fine[split] == 4 * coarse[split]).all())
    assert bool((coarse[~split] == fine[~split]).all())
    area = torch.zeros(F, dtype=D).index_add(0, p.coarse.leaf_user, p.coarse.leaves.areas)
    torch.testing.assert_close(area, groove.areas, rtol=1e-12, atol=0)
    assert bool((p.extrapolation[split] > 0).all()) and bool((p.extrapolation[~split] == 0).all())


def test_one_refinement_extrapolated_with_two_thirds(groove, groove_fitted_reference):
    """After the first split no convergence ratio is known: the output is extrapolated with c = 2/3 (the middle of
    c in [1/3, 1], orders 2 to 1) and estimated at a third of the change, so at 1.2e-2 one refinement is enough
    here (discretisation estimate 7.9e-3 against its share 9.6e-3). Measured against the fitted-order reference:
    8.3e-5 (the last level alone 1.56e-2), estimated 9.1e-3. The rule before (c = 1, estimate = the change) refined
    twice (80 leaves) and reached 1.2e-3."""
    r = _grey(groove, 0.8)
    p = plan(groove, r, "uniform", ONE, wavelengths=WL, accuracy=1.2e-2)
    assert p.report.iterations == 1 and p.report.leaves == 4 * groove.num_facets
    torch.testing.assert_close(p.extrapolation, torch.full_like(p.extrapolation, 2 / 3), rtol=0, atol=1e-15)
    err = _rel_rms(p.apply(r, ONE).irradiance[:, 0], groove_fitted_reference)
    last = dataclasses.replace(p, coarse=None, extrapolation=None).apply(r, ONE).irradiance[:, 0]
    assert err <= p.report.estimated <= 1.2e-2
    assert err <= _rel_rms(last, groove_fitted_reference) / 100


def test_a_measured_ratio_extrapolates_every_split_facet():
    """On this W fold the later refinements measure the convergence ratio (0.33, 0.22 and 0.15, clamped to 1/3):
    every facet split so far is then extrapolated with c = 0.5 instead of the default 2/3, those that the later
    steps left alone included; facets with ray-cast visibility are not extrapolated. The result is within its
    estimate: measured 2.1e-3 (estimated 2.5e-3) against a first-order extrapolation of uniform k = 6 and 12."""
    from torch_interreflect.accuracy.refine import Q_MIN

    w = ti.scenes.w_shape(divisions=(2, 4, 2), dtype=D)
    p = plan(w, _grey(w, 0.7), "uniform", ONE, wavelengths=WL, accuracy=3e-3)
    c, n = p.extrapolation, p.report.leaves_per_facet
    assert p.report.iterations >= 3 and bool((c == 0).any())
    assert bool(((c > 0) & (n == 4)).any()) and bool(((c > 0) & (n > 4)).any())  # split once, and again
    torch.testing.assert_close(c[c > 0], torch.full_like(c[c > 0], Q_MIN / (1 - Q_MIN)), rtol=0, atol=1e-12)
    E = p.apply(_grey(w, 0.7), ONE).irradiance[:, 0]
    ref = _uniform_reference(w, 0.7, "uniform")
    err = float(((E - ref) / ref).square().mean().sqrt())
    assert err <= p.report.estimated <= 3e-3


def test_the_solvers_closure_warning_is_raised_once_per_render():
    """A closed float32 box at r = 0.99: the form factors' closure error, amplified ~100×, is above every solve's
    tolerance. The planning solves (the level, the a-priori estimate) used to repeat the solver's warning (3 in all
    for this render); only the solve of the chosen plan raises it now, and the result is still E0 / (1 − r)."""
    box = ti.scenes.closed_box(1.0, divisions=2, dtype=torch.float32)
    r = 0.99
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = render(box, _grey(box, r, torch.float32), "uniform", torch.ones(1), accuracy=2e-2,
                        wavelengths=WL.float(), progress=False)
    solver = [w for w in caught if issubclass(w.category, AccuracyWarning) and str(w.message).startswith("solve(")]
    assert len(solver) == 1
    e = out.irradiance[:, 0].double()
    assert float(((e - 1 / (1 - r)) / (1 / (1 - r))).abs().max()) < 3e-3  # measured 1.3e-3
