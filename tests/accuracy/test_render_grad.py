"""Gradients of ``render`` / ``Plan.apply`` with respect to the geometry and the light's direction.

Oracle: central finite differences of :meth:`Plan.for_geometry` (the same refinement on the moved scene) with a
step of 0.01° / 1e-3: the planned quadrature picks its Gauss orders from the geometry, so ``F`` has jumps of ~1e-7
that smaller steps amplify; at this step the quadrature's own jumps are below 1e-4 of the derivative.
"""

from __future__ import annotations

import dataclasses
import warnings

import pytest
import torch

import torch_interreflect as ti
from torch_interreflect.errors import ShapeError

F64 = torch.float64


def _plan(angle: torch.Tensor, light="uniform"):
    r = torch.linspace(0.5, 0.9, 8, dtype=F64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        p = ti.accuracy.plan(ti.scenes.v_groove(angle, divisions=2), r, light, accuracy=2e-2)
    return p, r


#: a sun down the groove's opening (between the plates' normals): every leaf fully lit, no shadow edge to cross
SUN = [-0.7, 0.1, -0.4]


def test_planning_a_scene_whose_corners_require_grad_warns_nothing():
    """The planner's bookkeeping (RMS of estimates, the solution's spread) works on detached values: no
    "converting a tensor with requires_grad=True to a scalar" warning (the README's snippet printed one)."""
    a = torch.tensor(50.0, dtype=F64, requires_grad=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        p = ti.accuracy.plan(ti.scenes.v_groove(a, divisions=2), torch.full((8,), 0.8, dtype=F64), SUN,
                             accuracy=2e-2)
    assert p.report.iterations == 1


@pytest.mark.parametrize("light", ["uniform", "sky", SUN])
def test_render_passes_gradients_to_the_groove_angle(light):
    """d sum(E) / d angle through the refined leaves equals central differences of the same refinement on the
    moved groove (measured 1.5e-4 to 2.5e-4 relative); the values are the plan's (straight-through)."""
    a = torch.tensor(50.0, dtype=F64, requires_grad=True)
    p, r = _plan(a, light)
    assert p.report.leaves > 8
    out = p.apply(r)
    with torch.no_grad():
        assert torch.allclose(out.irradiance, p.apply(r).irradiance, rtol=1e-12, atol=0)
    (g,) = torch.autograd.grad(out.irradiance.sum(), a)

    def f(x: float) -> float:
        moved = p.for_geometry(ti.scenes.v_groove(torch.tensor(x, dtype=F64), divisions=2))
        return float(moved.apply(r).irradiance.sum())

    h = 1e-2
    fd = (f(50.0 + h) - f(50.0 - h)) / (2 * h)
    assert abs(fd) > 1.0
    assert abs(float(g) - fd) <= 1e-3 * abs(fd), (float(g), fd)


def test_render_passes_gradients_to_a_sun_direction():
    """Cosines and the interreflected light move with the sun (lit fractions are constants: here all 1)."""
    d = torch.tensor(SUN, dtype=F64, requires_grad=True)
    p, r = _plan(torch.tensor(50.0, dtype=F64), d)
    (g,) = torch.autograd.grad(p.apply(r).irradiance.sum(), d)

    def f(x: torch.Tensor) -> float:
        return float(dataclasses.replace(p, light=x).for_geometry(p.scene).apply(r).irradiance.sum())

    h = 1e-3
    fd = torch.tensor([(f(d.detach() + h * e) - f(d.detach() - h * e)) / (2 * h) for e in torch.eye(3, dtype=F64)])
    assert float(g.abs().max()) > 10.0
    assert float((g - fd).abs().max()) <= 5e-5 * float(g.abs().max()), (g, fd)  # measured 1.0e-5


def test_for_geometry_checks_the_facets():
    a = torch.tensor(50.0, dtype=F64, requires_grad=True)
    p, _ = _plan(a)
    with pytest.raises(ShapeError, match="for_geometry needs the plan's 8 facets"):
        p.for_geometry(ti.scenes.v_groove(50.0, divisions=3, dtype=F64))


def test_render_image_passes_gradients_to_the_angle():
    """``Plan.apply(view=)`` (flat shading; a plan that keeps the user's facets): the image is the rendered coverage
    times the facets' radiance, so d(weighted image)/d angle is the rendered coverage times the radiance's
    differences plus the radiance times the exact coverage's differences (measured 1.5e-6 relative: the plan's
    quadrature at a 1e-3° step)."""
    from tests.oracles import polygon_pixel_areas

    view = ti.View((0.08, 0.045, 0.05), (0.02, 0.045, 0.01), up=(0, 1, 0), fov_deg=60, height=12, width=12)
    r = torch.linspace(0.5, 0.9, 8, dtype=F64)
    a = torch.tensor(50.0, dtype=F64, requires_grad=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        p = ti.accuracy.plan(ti.scenes.v_groove(a, divisions=2), r, "uniform", accuracy=0.1)
    assert p.report.leaves == 8
    out = p.apply(r, view=view, shading="flat")
    w = torch.rand(out.image.shape, dtype=F64, generator=torch.Generator().manual_seed(0))
    (g,) = torch.autograd.grad((out.image * w).sum(), a)
    pin = view.pinhole()
    rendered = ti.camera.gather_operator(p.leaves, view, shading="flat").coverage.to_dense().T.reshape(8, 12, 12)

    def parts(x: float) -> tuple[torch.Tensor, torch.Tensor]:
        scene = ti.scenes.v_groove(torch.tensor(x, dtype=F64), divisions=2)
        with torch.no_grad():
            radiance = p.for_geometry(scene).apply(r).radiance  # [8, L]
        return radiance, torch.stack([polygon_pixel_areas(pin.project(q), 12, 12) for q in scene.corners])

    h = 1e-3
    (rp, cp), (rm, cm), (r0, _) = parts(50.0 + h), parts(50.0 - h), parts(50.0)
    fd = float((torch.einsum("fl,fhw->lhw", (rp - rm) / (2 * h), rendered) * w).sum()
               + (torch.einsum("fl,fhw->lhw", r0, (cp - cm) / (2 * h)) * w).sum())
    assert abs(fd) > 1.0
    assert abs(float(g) - fd) <= 5e-6 * abs(fd), (float(g), fd)


def test_a_replaced_scene_moves_both_levels_of_an_extrapolated_plan():
    """``dataclasses.replace(plan, scene=...)`` with corners that require grad: the coarse level follows the new
    scene too, so the gradient is the one of the plan built on that scene (before the coarse level took the
    parent's scene, only the fine level carried it: 42 % off)."""
    a = torch.tensor(50.0, dtype=F64, requires_grad=True)
    p, r = _plan(a)
    assert p.report.extrapolated and p.coarse is not None
    (g,) = torch.autograd.grad(p.apply(r).irradiance.sum(), a)
    b = torch.tensor(50.0, dtype=F64, requires_grad=True)
    q = dataclasses.replace(p, scene=ti.scenes.v_groove(b, divisions=2))
    (g2,) = torch.autograd.grad(q.apply(r).irradiance.sum(), b)
    torch.testing.assert_close(g2, g, rtol=1e-12, atol=0)
