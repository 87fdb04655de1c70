"""Gradients of the direct light ``E0`` with respect to the light direction and the scene's geometry.

Oracles: float64 ``gradcheck`` (central finite differences). Lit fractions (shadows) and ray-cast sky fractions are
constants of the geometry (documented in :mod:`torch_interreflect.lights`); a finite-difference step of 1e-6 does
not move a shadow ray across an edge, so the checks hold with shadows on.
"""

from __future__ import annotations

import math

import torch

import torch_interreflect as ti
from torch_interreflect.lights import light_geometry

F64 = torch.float64
ONE = torch.ones(1, dtype=F64)


def test_gradcheck_sun_direction_with_shadows():
    # a W fold: the ridge casts shadows on the outer plates (lit fractions strictly between 0 and 1)
    scene = ti.scenes.w_shape(60.0, divisions=(2, 4, 2), dtype=F64)
    d = torch.tensor([1.0, 0.1, -1.0], dtype=F64, requires_grad=True)
    lit = ti.lights.lit_fraction(scene, d)
    assert bool(((lit > 0) & (lit < 1)).any()) and not lit.requires_grad
    assert torch.autograd.gradcheck(lambda x: ti.lights.directional(scene, x, ONE)[:, 0], (d,), eps=1e-6,
                                    atol=1e-8, rtol=1e-6)


def test_gradcheck_sun_on_a_groove_angle():
    d = torch.tensor([0.3, 0.0, -1.0], dtype=F64)
    angle = torch.tensor(70.0, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda a: ti.lights.directional(ti.scenes.v_groove(a, divisions=2), d, ONE)[:, 0], (angle,), eps=1e-6,
        atol=1e-8, rtol=1e-6)


def test_sun_gradient_is_the_cosine_derivative():
    # one facet facing +z: E0 = cos θ = -d_z / |d|
    scene = ti.scenes.v_groove(90.0, divisions=1, dtype=F64)
    d = torch.tensor([0.6, 0.0, -0.8], dtype=F64, requires_grad=True)
    (g,) = torch.autograd.grad(ti.lights.directional(scene, d, ONE, shadows=False)[0, 0], d)
    expected = torch.tensor([-0.8 * 0.6, 0.0, -1 + 0.8 * 0.8], dtype=F64)  # d(-d_z / |d|) / dd at |d| = 1
    assert torch.allclose(g, expected, atol=1e-14)


def test_gradcheck_sky_open_fraction_on_a_groove_angle():
    def sky(a):
        scene = ti.scenes.v_groove(a, divisions=2)
        return ti.lights.sky(scene, ti.form_factors(scene), ONE)[:, 0]

    angle = torch.tensor(50.0, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(sky, (angle,), eps=1e-6, atol=1e-8, rtol=1e-6)


def test_light_geometry_keeps_the_gradients():
    angle = torch.tensor(60.0, dtype=F64, requires_grad=True)
    scene = ti.scenes.v_groove(angle, divisions=2)
    K = ti.form_factors(scene)
    mask = torch.zeros(scene.num_facets, dtype=torch.bool)
    mask[0] = True
    for light in ("sky", mask, [0.2, 0.0, -1.0]):
        g = light_geometry(scene, K, light)
        assert g.requires_grad, light
    # the sky's factor by hand: π (1 − Σ_j F_ij), its gradient that of the row sums
    (g_sky,) = torch.autograd.grad(light_geometry(scene, K, "sky").sum(), angle, retain_graph=True)
    (g_rows,) = torch.autograd.grad(K.row_sums().sum(), angle)
    assert torch.allclose(g_sky, -math.pi * g_rows, rtol=1e-12)
