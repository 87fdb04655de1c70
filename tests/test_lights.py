import math

import pytest
import torch

import torch_interreflect as ti
from torch_interreflect.errors import ShapeError, ValueRangeError


def test_directional_cosine_law_without_shadows(dtype):
    s = ti.scenes.v_groove(90.0, divisions=1, dtype=dtype)
    d = torch.tensor([-1.0, 0.0, -1.0], dtype=dtype)  # 45° from above, travelling toward -x
    spd = torch.linspace(1.0, 2.0, 5, dtype=dtype)
    E0 = ti.lights.directional(s, d, spd, shadows=False)
    assert E0.shape == (2, 5) and E0.dtype == dtype
    c = math.cos(math.radians(45.0))
    torch.testing.assert_close(E0[0], c * spd)  # floor faces +z
    torch.testing.assert_close(E0[1], c * spd)  # wall faces +x: the light comes from +x


def test_v_groove_shadow_from_the_overhanging_plate():
    # 45° groove, light straight down: plate B overhangs plate A up to x = w cos 45°
    w = 0.06
    s = ti.scenes.v_groove(45.0, size=(0.09, w), divisions=(1, 60), dtype=torch.float64)
    lit = ti.lights.lit_fraction(s, torch.tensor([0.0, 0.0, -1.0]), shadow_samples=2)
    plate_a = lit[:60]
    x = s.centroids[:60, 0]
    shadow_edge = w * math.cos(math.radians(45.0))
    assert bool((plate_a[x < shadow_edge - 0.002] == 0).all())
    assert bool((plate_a[x > shadow_edge + 0.002] == 1).all())
    lit_area = float((plate_a * s.areas[:60]).sum() / s.areas[:60].sum())
    assert abs(lit_area - (1 - shadow_edge / w)) < 0.01
    assert bool((lit[60:] == 0).all())  # plate B faces away from the light


def test_directional_batch_of_spectra_and_gradients():
    s = ti.scenes.box_corner(divisions=2, dtype=torch.float64)
    spd = torch.rand(4, 7, dtype=torch.float64, requires_grad=True)
    E0 = ti.lights.directional(s, torch.tensor([-1.0, -2.0, -3.0], dtype=torch.float64), spd)
    assert E0.shape == (4, s.num_facets, 7)
    # an inside corner lit from (+, +, +): nothing shades; E0_i = spd · n_i·(−d)/|d| (floor z, walls x and y)
    cos = s.normals @ torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64) / 14**0.5
    assert float(cos.min()) > 0
    torch.testing.assert_close(E0, cos[:, None] * spd[:, None, :], rtol=1e-12, atol=0)
    E0.sum().backward()
    assert spd.grad is not None and bool((spd.grad > 0).all())


def test_sky_from_escaping_rays_matches_the_form_factors_where_both_are_exact():
    """Escaping rays (low-discrepancy points and directions) against 1 − Σ_j F_ij of an unoccluded V-groove
    (measured: 2.8e-3 at most)."""
    from torch_interreflect.formfactors.hemisphere import hemisphere_fractions

    s = ti.scenes.v_groove(60.0, size=(1.0, 1.0), divisions=2, dtype=torch.float64)
    escape, back = hemisphere_fractions(s, torch.arange(s.num_facets), samples=12, points=8)
    torch.testing.assert_close(escape, 1 - ti.form_factors(s).row_sums(), rtol=0, atol=4e-3)
    assert float(back.abs().max()) == 0.0


def test_hemisphere_rays_compiled_and_numpy_agree(monkeypatch):
    """The compiled ray set-up and its numpy twin (no numba) cast the same rays: same fractions to rounding, on a
    Cornell box whose floor sees the blocks' open bottoms (back coverage up to 0.32)."""
    from torch_interreflect.formfactors import compiled
    from torch_interreflect.formfactors.hemisphere import hemisphere_fractions

    c = ti.scenes.cornell_box(3)
    idx = torch.arange(c.num_facets)
    e1, b1 = hemisphere_fractions(c, idx, samples=8, points=4)
    with monkeypatch.context() as m:
        m.setenv("TI_DISABLE_NUMBA", "1")
        compiled.loops.cache_clear()
        e2, b2 = hemisphere_fractions(c, idx, samples=8, points=4)
    compiled.loops.cache_clear()
    assert float(b1.max()) > 0.2 and float(e1.max()) > 0.2
    torch.testing.assert_close(e1, e2, rtol=0, atol=1e-12)
    torch.testing.assert_close(b1, b2, rtol=0, atol=1e-12)


def test_sky_is_pi_l_times_the_open_part():
    s = ti.scenes.v_groove(90.0, size=(1.0, 1.0), divisions=1, dtype=torch.float64)
    K = ti.form_factors(s)
    E0 = ti.lights.sky(s, K, torch.tensor([2.0], dtype=torch.float64))
    torch.testing.assert_close(E0[:, 0], torch.full((2,), 2 * math.pi * (1 - 0.2000438), dtype=torch.float64),
                               rtol=1e-6, atol=0)
    closed = ti.scenes.closed_box(divisions=2, dtype=torch.float64)
    E0c = ti.lights.sky(closed, ti.form_factors(closed), torch.ones(3, dtype=torch.float64))
    assert float(E0c.abs().max()) < 1e-5  # a closed box sees no sky


def test_uniform_light(dtype):
    s = ti.scenes.box_corner(divisions=1, dtype=dtype)
    spd = torch.rand(2, 31, dtype=dtype, generator=torch.Generator().manual_seed(0))
    E0 = ti.lights.uniform(s, spd)
    assert E0.shape == (2, 3, 31) and E0.dtype == dtype
    for i in range(3):  # every facet gets the spectrum itself
        torch.testing.assert_close(E0[:, i], spd, rtol=0, atol=0)


def test_light_geometry_takes_scene_form_factors_light_and_the_old_order_warns():
    s = ti.scenes.v_groove(90.0, size=(1.0, 1.0), divisions=1, dtype=torch.float64)
    K = ti.form_factors(s)
    g = ti.lights.light_geometry(s, K, "sky")
    torch.testing.assert_close(g, torch.full((2,), math.pi * (1 - 0.2000438), dtype=torch.float64), rtol=1e-6, atol=0)
    torch.testing.assert_close(ti.lights.light_geometry(None, K, "sky"), g)
    with pytest.warns(DeprecationWarning, match=r"light_geometry\(scene, form_factors, light\)"):
        old = ti.lights.light_geometry("sky", K)
    torch.testing.assert_close(old, g)
    with pytest.warns(DeprecationWarning):
        old = ti.lights.light_geometry([0.0, 0.0, -1.0], K, s)
    assert old.tolist() == [1.0, 0.0]
    with pytest.warns(DeprecationWarning, match="shadow_samples"):
        ti.lights.lit_fraction(s, torch.tensor([0.0, 0.0, -1.0]), samples=2)
    with pytest.warns(DeprecationWarning, match="sky_samples"):
        ti.lights.sky(s, K, torch.ones(1, dtype=torch.float64), samples=4)


def test_bad_light_input():
    s = ti.scenes.box_corner(divisions=1)
    with pytest.raises(ValueRangeError, match="non-negative"):
        ti.lights.uniform(s, -torch.ones(3))
    with pytest.raises(ValueRangeError, match="finite"):
        ti.lights.directional(s, torch.tensor([0.0, 0, -1]), torch.tensor([math.nan]))
    with pytest.raises(ValueRangeError, match="nonzero 3-vector"):
        ti.lights.directional(s, torch.zeros(3), torch.ones(3))
    with pytest.raises(ShapeError, match="3 components"):
        ti.lights.directional(s, torch.ones(2), torch.ones(3))
    other = ti.form_factors(ti.scenes.box_corner(divisions=2))
    with pytest.raises(ShapeError, match="facets"):
        ti.lights.sky(s, other, torch.ones(3))


def _bottomless_box_on_floor():
    """A unit floor with a bottomless box over its centre quarter: that quarter sees only the box's inside."""
    floor = ti.scenes.grid_quads([0, 0, 0], [1, 0, 0], [0, 1, 0], 1, 1)
    lo, hi, h = 0.25, 0.75, 0.3
    ex, ey, ez = [hi - lo, 0, 0], [0, hi - lo, 0], [0, 0, h]
    box = [
        ti.scenes.grid_quads([lo, lo, h], ex, ey, 1, 1),  # lid, facing up
        ti.scenes.grid_quads([lo, lo, 0], ex, ez, 1, 1),  # side y=lo, facing -y (normal = a × b)
        ti.scenes.grid_quads([lo, hi, 0], ez, ex, 1, 1),  # side y=hi, facing +y
        ti.scenes.grid_quads([lo, lo, 0], ez, ey, 1, 1),  # side x=lo, facing -x
        ti.scenes.grid_quads([hi, lo, 0], ey, ez, 1, 1),  # side x=hi, facing +x
    ]
    import numpy as np

    return ti.Scene.from_polygons(torch.tensor(np.concatenate([floor, *box]), dtype=torch.float64))


def test_sky_discounts_back_faces_seen_from_under_a_block():
    scene = _bottomless_box_on_floor()
    b = ti.lights.back_coverage(scene)
    # 16 of the 8 × 8 points lie under the box, fully covered (a ray-cast estimate: rays grazing the seam
    # between the floor and the walls can slip out)
    assert abs(float(b[0]) - 0.25) < 0.01
    assert bool((b[1:] == 0).all())
    K = ti.form_factors(scene)
    E0 = ti.lights.sky(scene, K, torch.ones(1, dtype=torch.float64))
    expected = math.pi * (1 - float(K.row_sums()[0]) - float(b[0]))
    # the floor's pairs with the box need visibility rays, so its open part is counted from escaping rays
    assert bool(K.info["occluded_facets"][0])
    assert abs(float(E0[0, 0]) - expected) < 0.01 * math.pi
    plain = ti.lights.sky(scene, K, torch.ones(1, dtype=torch.float64), backfaces=False)
    assert float(plain[0, 0]) > float(E0[0, 0])


def test_sky_on_some_facets_equals_those_rows_of_the_full_call():
    """``facets=``: the rows of a subset, bit for bit (rays are seeded per facet): escaping rays on the occluded
    facets, back coverage and ``1 − Σ_j F_ij`` on the others, in any order; bad indices raise."""
    box = _bottomless_box_on_floor().subdivide(2)[0]
    K = ti.form_factors(box)
    occ = K.info["occluded_facets"]
    assert bool(occ.any()) and bool((~occ).any())
    spd = torch.tensor([[1.0, 2.0]], dtype=torch.float64)
    some = torch.tensor([20, 3, 17, 0, 23, 9, 12, 5])
    for backfaces in ("auto", True):  # True: back rays from the lid's facets too
        full = ti.lights.sky(box, K, spd, backfaces=backfaces)
        assert torch.equal(ti.lights.sky(box, K, spd, backfaces=backfaces, facets=some), full[..., some, :])
    assert ti.lights.sky(box, K, spd, facets=some[:0]).shape == (1, 0, 2)
    with pytest.raises(ValueRangeError, match=r"\[0, 24\)"):
        ti.lights.sky(box, K, spd, facets=torch.tensor([24]))
    with pytest.raises(ShapeError, match="integer tensor"):
        ti.lights.sky(box, K, spd, facets=torch.tensor([0.5]))
    with pytest.raises(ShapeError, match="integer tensor"):  # a mask is not indices
        ti.lights.sky(box, K, spd, facets=torch.zeros(24, dtype=torch.bool))


@pytest.mark.parametrize("kw", [dict(sky_samples=0), dict(sky_samples=2.5), dict(sky_samples=True)])
def test_bad_sky_sample_counts_raise(kw):
    """Checked up front, even where no facet needs rays (an open V-groove)."""
    s = ti.scenes.v_groove(60.0, divisions=1, dtype=torch.float64)
    with pytest.raises(ti.errors.ValueRangeError, match="sky_samples"):
        ti.lights.sky(s, ti.form_factors(s), torch.ones(1, dtype=torch.float64), **kw)
    with pytest.raises(ti.errors.ValueRangeError, match="sky_samples"):
        ti.lights.back_coverage(s, **kw)


def test_bad_hemisphere_point_count_raises():
    from torch_interreflect.formfactors.hemisphere import hemisphere_fractions

    s = ti.scenes.v_groove(60.0, divisions=1, dtype=torch.float64)
    with pytest.raises(ti.errors.ValueRangeError, match="points"):
        hemisphere_fractions(s, torch.arange(2), samples=4, points=0)


def test_sun_direction_is_one_rule_for_every_stage() -> None:
    """lights, the gather and its image gradient read a light as a direction by the same rule."""
    from torch_interreflect.lights import sun_direction

    d = torch.tensor([0.2, 0.1, -1.0], requires_grad=True)
    assert sun_direction(d, 8) is d  # as given: gradients kept
    assert sun_direction([0, 0, -1], 8).tolist() == [0, 0, -1]
    assert sun_direction([0.2, 0.1, 0.3], 3) is None  # three facets: g [F]
    assert sun_direction(torch.tensor([True, False, True]), 8) is None  # a mask
    assert sun_direction("sky", 8) is None and sun_direction(None, 8) is None
    assert sun_direction(torch.ones(2, 3), 8) is None
