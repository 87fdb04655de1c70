"""The Levenberg–Marquardt refinement: its image model, Jacobian and least-squares fit against oracles."""

from __future__ import annotations

import math

import pytest
import torch

from torch_interreflect import spectral
from torch_interreflect.camera import Camera
from torch_interreflect.camera.gather import gathered_image, source_irradiance
from torch_interreflect.errors import ValueRangeError
from torch_interreflect.formfactors import FormFactors
from torch_interreflect.solver import radiance, solve
from torch_interreflect.training import generator as g
from torch_interreflect.training import refine as refine_module
from torch_interreflect.training import refine_illuminant
from torch_interreflect.training.least_squares import scaled_least_squares
from torch_interreflect.training.metrics import angular_error
from torch_interreflect.training.refine import _decode, _problem, _tangents, gathered_model
from torch_interreflect.training.rerender import MaterialImage, reciprocity_error


@pytest.fixture(scope="module")
def sample() -> dict:
    cfg = g.GeneratorConfig(size=(16, 16), scenes=("cornell",), seed=2)
    s = g.render_sample(cfg, 0)
    geo = g.load_geometry(s.geometry)
    image = torch.from_numpy(s.images[None]).permute(2, 0, 1).double()
    truth = torch.tensor(s.metadata["illuminant"]["rgb_normalized"], dtype=torch.float64)
    wl = spectral.wavelengths(*cfg.wavelengths, dtype=torch.float64)
    return {"cfg": cfg, "geo": geo, "image": image, "truth": truth, "cam": Camera.from_colour(cfg.camera, wl)}


def _model(sample: dict, bounces: int | None, flat: bool = False) -> tuple[MaterialImage, torch.Tensor]:
    geo = sample["geo"]
    cov, _, material = _problem(sample["image"], geo)
    seen = geo["coverage"].to_dense().sum(1) > 1e-9
    pixels = None if flat else gathered_model(geo)
    return MaterialImage(geo["form_factors"], geo["light_factor"], material, sample["cam"], pixels, seen, cov,
                         bounces), seen


def _symmetric(ff: FormFactors) -> FormFactors:
    """``F`` made exactly reciprocal, as the model's symmetric form (``A F`` averaged with its transpose)."""
    am = ff.areas[:, None] * ff.matrix.to_dense()
    return FormFactors(0.5 * (am + am.T) / ff.areas[:, None], ff.areas)


def _spectra(n_mat: int) -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(0)
    spd = 0.5 + torch.rand(31, generator=gen, dtype=torch.float64)
    refl = 0.05 + 0.85 * torch.rand(n_mat, 31, generator=gen, dtype=torch.float64)
    return spd, refl


@pytest.mark.parametrize("bounces", [None, 1, 2, 3])
def test_the_material_image_is_the_gathered_image(sample: dict, bounces: int | None) -> None:
    model, seen = _model(sample, bounces)
    geo = sample["geo"]
    spd, refl = _spectra(model.num_materials)
    r_f = refl[geo["material"].long()]
    op, direct = gathered_model(geo)
    images = []
    for f in (_symmetric(geo["form_factors"]), geo["form_factors"]):
        E = source_irradiance(f, r_f, geo["light_factor"][:, None] * spd, bounces, method="dense")
        images.append(gathered_image(op, r_f, E, spd, sample["cam"], direct=direct).reshape(3, -1).T[seen])
    got = model(spd, refl)
    top = float(images[0].abs().max())
    if bounces is None:  # measured: 3.4e-16 of the largest pixel against the symmetric form; 8.1e-10 against F
        # itself, which is reciprocal to 7e-8 here
        torch.testing.assert_close(got, images[0], atol=3e-15 * top, rtol=0)
        torch.testing.assert_close(got, images[1], atol=4e-9 * top, rtol=0)
    else:  # the finite series multiplies by F itself; measured: 4.5e-16 to 6.8e-16
        torch.testing.assert_close(got, images[1], atol=3e-15 * top, rtol=0)


@pytest.mark.parametrize("bounces", [None, 2])
def test_the_flat_material_image_is_coverage_times_camera_radiance(sample: dict, bounces: int | None) -> None:
    model, _ = _model(sample, bounces, flat=True)
    geo = sample["geo"]
    cov, _, material = _problem(sample["image"], geo)
    spd, refl = _spectra(model.num_materials)
    r_f = refl[material]
    ff = _symmetric(geo["form_factors"]) if bounces is None else geo["form_factors"]
    E = solve(ff, r_f, geo["light_factor"][:, None] * spd, bounces=bounces, method="dense")
    ref = cov @ sample["cam"](radiance(E, r_f))
    # measured: 4.5e-16 of the largest pixel
    torch.testing.assert_close(model(spd, refl), ref, atol=3e-15 * float(ref.abs().max()), rtol=0)


@pytest.mark.parametrize(("bounces", "flat"), [(None, False), (2, False), (None, True), (3, True)])
def test_the_jacobian_is_the_central_difference(sample: dict, bounces: int | None, flat: bool) -> None:
    model, _ = _model(sample, bounces, flat)
    spd, refl = _spectra(model.num_materials)
    gen = torch.Generator().manual_seed(1)
    n_dir = 4
    spd_t = torch.randn(n_dir, 31, generator=gen, dtype=torch.float64)
    refl_t = 0.1 * torch.randn(n_dir, model.num_materials, 31, generator=gen, dtype=torch.float64)
    p, jac = model.jacobian(spd, refl, spd_t, refl_t)
    torch.testing.assert_close(p, model(spd, refl), atol=0, rtol=1e-13)
    h = 1e-5
    for k in range(n_dir):
        up, down = model(spd + h * spd_t[k], refl + h * refl_t[k]), model(spd - h * spd_t[k], refl - h * refl_t[k])
        fd = (up - down) / (2 * h)
        # measured: 1.5e-10–1.8e-10 of the largest entry in the four cases
        torch.testing.assert_close(jac[k], fd, atol=1e-9 * float(fd.abs().max()), rtol=0)


def test_least_squares_reaches_an_exact_fit_up_to_the_scale() -> None:
    t = torch.linspace(0, 1, 40, dtype=torch.float64)

    def model(th: torch.Tensor) -> torch.Tensor:
        return torch.exp(th[0] * t) + th[1] * t.square()

    def jac(th: torch.Tensor, free: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        full = torch.stack([t * torch.exp(th[0] * t), t.square()], 1)
        return model(th), full[:, free]

    truth = torch.tensor([-1.3, 0.7], dtype=torch.float64)
    obs = 3.0 * model(truth)  # any scale: projected out
    zero = torch.zeros(2, dtype=torch.float64)
    fit = scaled_least_squares(model, jac, obs, torch.tensor([0.5, 0.0], dtype=torch.float64), zero, zero,
                               torch.arange(2), max_steps=100, rtol=1e-14)
    # measured: 6.7e-16 from the truth after 7 steps, misfit 2e-32 of ‖o‖²
    torch.testing.assert_close(fit.theta, truth, atol=5e-15, rtol=0)
    assert fit.misfit < 2e-31 * float(obs @ obs) and fit.steps <= 12
    only = scaled_least_squares(model, jac, obs, torch.tensor([-1.3, 0.0], dtype=torch.float64), zero, zero,
                                torch.tensor([1]), max_steps=100, rtol=1e-14)
    assert float(only.theta[0]) == -1.3  # a fixed entry stays
    torch.testing.assert_close(only.theta, truth, atol=1e-15, rtol=0)  # measured: exact
    held = scaled_least_squares(model, jac, obs, torch.tensor([0.5, 0.0], dtype=torch.float64),
                                torch.tensor([0.0, 1e6], dtype=torch.float64), zero, torch.arange(2), max_steps=100,
                                rtol=1e-14)
    assert abs(float(held.theta[1])) < 2e-5  # a strong prior holds its entry at the centre; measured 2.1e-6
    # a moderate prior: at the result, the gradient of f (the scale optimal at every point) vanishes
    weights, centre = torch.tensor([1e-2, 3e-2], dtype=torch.float64), torch.tensor([0.2, -0.1], dtype=torch.float64)
    mid = scaled_least_squares(model, jac, obs, torch.tensor([0.5, 0.0], dtype=torch.float64), weights, centre,
                               torch.arange(2), max_steps=100, rtol=1e-15)
    th = mid.theta.clone().requires_grad_(True)
    p = model(th)
    f = (((p @ obs) / (p @ p)) * p - obs).pow(2).sum() + (weights * (th - centre).pow(2)).sum()
    (grad,) = torch.autograd.grad(f, th)
    # LM stops where no step lowers f in floating point: the gradient then sits at the rounding floor, about
    # sqrt(eps f h) ~ 1e-8 here, and where in it depends on the CPU's arithmetic. Measured 6.3e-10 (AMD EPYC) and
    # 2.6e-12 (an earlier machine), against 17.6 at the start and 0.048 with the prior's weights doubled in the fit
    assert float(grad.abs().max()) < 6.3e-9 and abs(mid.loss - float(f.detach())) < 1e-14

def test_levenberg_marquardt_fits_at_least_as_well_as_lbfgs(sample: dict) -> None:
    est = {"camera": sample["cfg"].camera, "wavelengths": sample["cfg"].wavelengths}
    start = torch.nn.functional.normalize(sample["truth"] * torch.tensor([1.2, 1.0, 0.85], dtype=torch.float64), dim=0)
    lm = refine_illuminant(est, sample["image"], sample["geo"], start)
    lb = refine_illuminant(est, sample["image"], sample["geo"], start, optimizer="lbfgs")
    assert lm.optimizer == "lm" and lb.optimizer == "lbfgs"
    e_start, e_lm, e_lb = (float(angular_error(x.float(), sample["truth"].float())) for x in (start, lm.rgb, lb.rgb))
    # measured: start 6.43°; LM 0.26° (residual 4.8e-4, 54 evaluations); L-BFGS 30.1° (residual 7.0e-3, 158): a
    # local minimum that Levenberg–Marquardt does not stop in
    assert lm.residual < 2e-3 and lm.residual <= lb.residual and e_lm < 0.1 * e_start, (lm, lb, e_start, e_lm, e_lb)
    assert lm.iterations < lb.iterations


def test_refine_checks_its_options(sample: dict) -> None:
    est = {"camera": sample["cfg"].camera, "wavelengths": sample["cfg"].wavelengths}
    with pytest.raises(ValueError, match="optimizer must be one of"):
        refine_illuminant(est, sample["image"], sample["geo"], sample["truth"], optimizer="adam")
    with pytest.raises(ValueRangeError, match="steps must be an integer"):
        refine_illuminant(est, sample["image"], sample["geo"], sample["truth"], steps=0)
    for bad in (1.0, -1e-4, float("nan")):
        with pytest.raises(ValueRangeError, match=r"stop_rtol must be a number in \[0, 1\)"):
            refine_illuminant(est, sample["image"], sample["geo"], sample["truth"], stop_rtol=bad)


def test_levenberg_marquardt_is_the_same_on_two_threads(sample: dict) -> None:
    est = {"camera": sample["cfg"].camera, "wavelengths": sample["cfg"].wavelengths}
    before = torch.get_num_threads()
    out = []
    try:
        for n in (1, 2):
            torch.set_num_threads(n)
            out.append(refine_illuminant(est, sample["image"], sample["geo"], sample["truth"], steps=8))
    finally:
        torch.set_num_threads(before)
    # measured: residuals 5.9e-13–6.6e-13 apart (relative), illuminants 2.2e-15–5.0e-15
    assert math.isclose(out[0].residual, out[1].residual, rel_tol=5e-12)
    torch.testing.assert_close(out[0].rgb, out[1].rgb, atol=2e-14, rtol=0)


def test_the_jacobian_is_the_symmetrised_models_when_f_is_not_quite_reciprocal(sample: dict) -> None:
    geo = sample["geo"]
    cov, _, material = _problem(sample["image"], geo)
    ff = geo["form_factors"]
    gen = torch.Generator().manual_seed(3)
    skew = ff.matrix.to_dense() * (1 + 5e-5 * torch.rand(ff.matrix.shape, generator=gen, dtype=torch.float64))
    bent = FormFactors(skew, ff.areas)
    assert 1e-5 < reciprocity_error(bent) < 1e-4  # within the solver's tolerance, far above rounding
    model = MaterialImage(bent, geo["light_factor"], material, sample["cam"], None, geo["coverage"].to_dense().sum(1)
                          > 1e-9, cov)
    spd, refl = _spectra(model.num_materials)
    refl_t = 0.1 * torch.randn(3, model.num_materials, 31, generator=gen, dtype=torch.float64)
    _, jac = model.jacobian(spd, refl, torch.zeros(3, 31, dtype=torch.float64), refl_t)
    h = 1e-5
    for k in range(3):
        fd = (model(spd, refl + h * refl_t[k]) - model(spd, refl - h * refl_t[k])) / (2 * h)
        # measured: 2.0e-10–6.2e-10 of the largest entry (4.4e-7–2.0e-6 with the tangent through F itself, while the
        # model goes through the symmetrised F)
        torch.testing.assert_close(jac[k], fd, atol=1e-9 * float(fd.abs().max()), rtol=0)


def test_the_parameter_tangents_are_the_decoders_derivatives() -> None:
    wl = spectral.wavelengths(dtype=torch.float64)
    basis = tuple(t.double() for t in spectral.illuminant_basis(wl, "Nikon 5100 (NPL)"))
    data = spectral.reflectance_data(wl)
    r_mean, r_comps = spectral.fit_reflectance_basis(data, 30)
    refl_basis = (r_mean, ((data - r_mean) @ r_comps.T).std(0), r_comps)
    k, m = basis[1].shape[0], 2
    gen = torch.Generator().manual_seed(4)
    theta = 0.5 * torch.randn(k + m * 30, generator=gen, dtype=torch.float64)
    theta[k:] *= 6  # reflectances far enough from the mean for the clamp to hold some samples
    _, _, spd_t, refl_t = _tangents(theta, basis, refl_basis, m)
    u = _decode(theta[:k], theta[k:].reshape(m, 30), basis, refl_basis)[2]
    inside = (u > 0.01) & (u < 0.95)
    assert bool(inside.any()) and not bool(inside.all())  # the clamp is met: its zero derivative is checked too
    h = 1e-6
    for p in [0, k - 1, k, k + 29, k + 30, k + 2 * 30 - 1]:
        e = torch.zeros_like(theta)
        e[p] = h
        up, down = (_decode(t[:k], t[k:].reshape(m, 30), basis, refl_basis) for t in (theta + e, theta - e))
        # measured: 9.7e-11–1.2e-10 of the largest derivative for S, 3.8e-11–1.2e-10 for R; 47 % of R's samples are
        # clamped here (their derivative 0)
        torch.testing.assert_close(spd_t[p], (up[1] - down[1]) / (2 * h), atol=1e-9 * float(spd_t.abs().max()), rtol=0)
        fd = (up[3] - down[3]) / (2 * h)
        keep = ((u - 0.01).abs() > 1e-4) & ((u - 0.95).abs() > 1e-4)  # away from the clamp's kinks
        torch.testing.assert_close(refl_t[p][keep], fd[keep], atol=1e-9, rtol=0)


def test_auto_takes_lbfgs_for_large_or_unreciprocal_scenes(sample: dict, monkeypatch: pytest.MonkeyPatch) -> None:
    est = {"camera": sample["cfg"].camera, "wavelengths": sample["cfg"].wavelengths}
    geo = sample["geo"]
    ff = geo["form_factors"]
    bent = {**geo, "form_factors": FormFactors(ff.matrix.to_dense() * (1 + 1e-2 * torch.rand(ff.matrix.shape,
                                                dtype=torch.float64, generator=torch.Generator().manual_seed(5))),
                                               ff.areas)}
    assert refine_illuminant(est, sample["image"], bent, sample["truth"], steps=2).optimizer == "lbfgs"
    with pytest.raises(ValueRangeError, match="reciprocal within"):
        refine_illuminant(est, sample["image"], bent, sample["truth"], steps=2, optimizer="lm")
    assert refine_illuminant(est, sample["image"], bent, sample["truth"], steps=2, bounces=2).optimizer == "lm"
    with pytest.raises(ValueRangeError, match="bounces must be None"):
        refine_illuminant(est, sample["image"], geo, sample["truth"], steps=2, bounces=0, optimizer="lm")
    monkeypatch.setattr(refine_module, "LM_MAX_FACETS", 0)
    assert refine_illuminant(est, sample["image"], geo, sample["truth"], steps=2).optimizer == "lbfgs"
