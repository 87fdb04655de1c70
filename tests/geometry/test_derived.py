"""The scene's derived values (areas, normals, centroids, diameters, its ray caster) are computed once while the
corners are unchanged, and never stale: after in-place writes, for corners that require grad, in inference mode."""

import pickle

import numpy as np
import pytest
import torch

import torch_interreflect as ti
from torch_interreflect.geometry import RayCaster, Scene
from torch_interreflect.geometry.derived import DerivedCache
from torch_interreflect.geometry.measures import facet_areas, facet_centroids, facet_diameters, facet_normals

MEASURES = {"areas": facet_areas, "normals": facet_normals, "centroids": facet_centroids,
            "diameters": facet_diameters}


def _scene(dtype=torch.float64, requires_grad=False):
    box = ti.scenes.closed_box(divisions=2, dtype=dtype)
    c = box.corners.clone().requires_grad_(requires_grad)
    return Scene.from_parts(c, box.is_triangle, box.material, box.material_names)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("name", sorted(MEASURES))
def test_kept_while_unchanged_and_made_again_after_an_in_place_write(name, dtype):
    sc = _scene(dtype)
    first = getattr(sc, name)
    assert getattr(sc, name) is first  # kept
    torch.testing.assert_close(first, MEASURES[name](sc.corners), rtol=0, atol=0)
    with torch.no_grad():
        sc.corners[:, :, 0] *= 2.0  # stretch along x: every measure but some normals changes
    again = getattr(sc, name)
    assert again is not first
    torch.testing.assert_close(again, MEASURES[name](sc.corners), rtol=0, atol=0)
    assert again.dtype == dtype


def test_a_kept_value_written_in_place_by_a_caller_is_made_again():
    sc = _scene()
    c = sc.centroids
    c.zero_()  # a caller's mistake must not reach the next reader
    torch.testing.assert_close(sc.centroids, facet_centroids(sc.corners), rtol=0, atol=0)


def test_corners_that_require_grad_are_never_kept_and_gradients_flow():
    sc = _scene(requires_grad=True)
    a, b = sc.areas, sc.areas
    assert a is not b and a.grad_fn is not None
    sc.areas.sum().backward()
    # the total area of the closed unit box is 6; each corner's gradient is that of facet_areas
    ref = sc.corners.detach().clone().requires_grad_(True)
    facet_areas(ref).sum().backward()
    torch.testing.assert_close(sc.corners.grad, ref.grad, rtol=0, atol=0)
    assert float(a.detach().sum()) == pytest.approx(6.0, rel=1e-12)


def test_inference_mode_keeps_nothing():
    sc = _scene()
    with torch.inference_mode():
        inside = sc.normals
    assert inside.is_inference()
    outside = sc.normals
    assert not outside.is_inference() and sc.normals is outside
    # an inference tensor could not be saved for backward: the kept one can
    w = torch.ones(3, dtype=torch.float64, requires_grad=True)
    (outside * w).sum().backward()
    torch.testing.assert_close(w.grad, outside.sum(0))


def test_to_and_detach_return_the_scene_itself_when_nothing_changes():
    sc = _scene()
    assert sc.to(torch.float64) is sc and sc.to("cpu") is sc and sc.detach() is sc
    other = sc.to(torch.float32)
    assert other is not sc and other.dtype == torch.float32
    g = _scene(requires_grad=True)
    d = g.detach()
    assert d is not g and not d.corners.requires_grad


def test_ray_caster_is_shared_and_follows_the_corners():
    sc = _scene()
    rc = RayCaster.of(sc)
    assert RayCaster.of(sc) is rc and RayCaster.of(sc.to(torch.float64)) is rc
    origin = np.array([[0.5, 0.5, 0.5]])
    up = np.array([[0.0, 0.0, 1.0]])
    hit = rc.first_hit(origin, up)
    with torch.no_grad():
        sc.corners[:, :, 2] += 10.0  # the box moves up: the ray from inside the old box now hits its floor
    rc2 = RayCaster.of(sc)
    assert rc2 is not rc
    np.testing.assert_array_equal(rc2.first_hit(origin, up), RayCaster(sc).first_hit(origin, up))
    assert rc2.first_hit(origin, up).tolist() != hit.tolist()
    assert RayCaster.of(_scene(requires_grad=True)) is not RayCaster.of(_scene(requires_grad=True))


def test_a_scene_with_kept_values_pickles():
    sc = _scene()
    RayCaster.of(sc)
    _ = sc.centroids
    back = pickle.loads(pickle.dumps(sc))
    torch.testing.assert_close(back.centroids, sc.centroids, rtol=0, atol=0)
    assert RayCaster.of(back) is not RayCaster.of(sc)


def test_cache_keys_on_the_source_object():
    cache, calls = DerivedCache(), []
    a, b = torch.zeros(3), torch.zeros(3)
    cache.get(a, "k", lambda: calls.append("a") or a + 1)
    cache.get(b, "k", lambda: calls.append("b") or b + 1)  # another tensor, same key: made again
    cache.get(b, "k", lambda: calls.append("b") or b + 1)
    assert calls == ["a", "b"]
    cache.clear()
    cache.get(b, "k", lambda: calls.append("b") or b + 1)
    assert calls == ["a", "b", "b"]


def test_writes_past_the_version_counter_need_clear_derived():
    """``corners.data`` has a counter of its own: such a write is not seen until ``clear_derived``."""
    sc = _scene()
    before = sc.areas
    sc.corners.data.mul_(2.0)
    assert sc.areas is before  # documented: not seen
    sc.clear_derived()
    torch.testing.assert_close(sc.areas, 4.0 * before, rtol=1e-15, atol=0)


def test_a_scene_with_kept_values_deep_copies():
    import copy

    sc = _scene()
    RayCaster.of(sc)
    dup = copy.deepcopy(sc)
    torch.testing.assert_close(dup.normals, sc.normals, rtol=0, atol=0)
    assert RayCaster.of(dup) is not RayCaster.of(sc) and dup.corners.data_ptr() != sc.corners.data_ptr()
