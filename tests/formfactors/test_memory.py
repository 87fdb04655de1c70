"""Scenes too large for the dense kernel (issue 13 item 5): a clear error before allocating, tested with a mocked
memory limit (nothing large is allocated)."""

import pytest
import torch

import torch_interreflect as ti
from torch_interreflect.errors import InsufficientMemoryError
from torch_interreflect.formfactors import memory


def test_form_factors_refuses_a_scene_larger_than_the_memory(monkeypatch):
    s = ti.scenes.closed_box(divisions=4, dtype=torch.float64)  # 96 facets: 3·96² B facing + 16·96² B dense
    need = memory.dense_kernel_bytes(96, None, True, 8)
    monkeypatch.setattr(memory, "available_memory", lambda: need - 1)
    with pytest.raises(InsufficientMemoryError, match=r"96 facets.*about 175.10 kB.*has 175.10 kB.*hierarchical_form"):
        ti.form_factors(s)
    # enough for the facing matrices but not for the pairs: refused after counting them
    monkeypatch.setattr(memory, "available_memory", lambda: need + 1000)
    with pytest.raises(InsufficientMemoryError, match=r"\d+ facet pairs"):
        ti.form_factors(s)
    monkeypatch.setattr(memory, "available_memory", lambda: 1 << 40)
    assert ti.form_factors(s).num_facets == 96


def test_the_estimate_of_a_200k_facet_scene_names_its_size():
    # the case of the issue: torch's raw "can't allocate 40392156484 bytes" at 200,000 facets
    with pytest.raises(InsufficientMemoryError, match=r"needs about 760.00 GB.*has 8.00 GB"):
        memory.check_memory(memory.dense_kernel_bytes(200_000), "form_factors on 200000 facets", "use x",
                            available=8 * 10**9)
    assert memory.available_memory() > 0


def test_lights_need_no_facing_matrix(monkeypatch):
    # before: lit_fraction(shadows="auto") and sky's back-face test built an [F, F] facing matrix
    from torch_interreflect.geometry import _polygon

    s = ti.scenes.cornell_box(divisions=1, dtype=torch.float64)
    d = torch.tensor([0.3, -1.0, 0.2], dtype=torch.float64)
    lit = ti.lights.lit_fraction(s, d)
    b = ti.lights.back_coverage(s)

    def refuse(*args, **kwargs):
        raise InsufficientMemoryError("an [F, F] facing matrix was requested")

    monkeypatch.setattr(_polygon, "facing_matrix", refuse)
    torch.testing.assert_close(ti.lights.lit_fraction(s, d), lit, rtol=0, atol=0)
    torch.testing.assert_close(ti.lights.back_coverage(s), b, rtol=0, atol=0)
