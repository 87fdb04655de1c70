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
from torch_interreflect.errors import GradientWarning, ShapeError

F64 = torch.float64


def _plan(angle: torch.Tensor, light="uniform"):
    r = torch.linspace(0.5, 0.9, 8, dtype=F64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        p = ti.accuracy.plan(ti.scenes.v_groove(angle, divisions=2), r, light, accuracy=2e-2)
    return p, r


#: a sun down the groove's opening (between the plates' normals): every leaf fully lit, no shadow edge to cross
SUN = [-0.7, 0.1, -0.4]


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


def test_for_geometry_checks_the_facets_and_the_image_warns():
    a = torch.tensor(50.0, dtype=F64, requires_grad=True)
    p, r = _plan(a)
    with pytest.raises(ShapeError, match="for_geometry needs the plan's 8 facets"):
        p.for_geometry(ti.scenes.v_groove(50.0, divisions=3, dtype=F64))
    view = ti.View((0.03, 0.03, 0.1), (0.03, 0.03, 0.0), (0, 1, 0), height=4, width=4)
    with pytest.warns(GradientWarning, match="per-pixel kernel"):
        p.apply(r, view=view)
    d = torch.tensor(SUN, dtype=F64, requires_grad=True)
    p_sun, r = _plan(torch.tensor(50.0, dtype=F64), d)
    with pytest.warns(GradientWarning, match="light's direction"):
        p_sun.apply(r, view=view)
