"""serial_torch: torch on one thread inside, the compiled loops and ray casting on the caller's count."""

import numpy as np
import pytest
import torch

import torch_interreflect as ti
from torch_interreflect._threads import loop_threads, serial_torch


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_serial_torch_keeps_the_callers_count_for_loops_and_restores_torch(threads):
    prev = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        assert loop_threads() == threads
        with serial_torch() as n:
            assert n == threads and torch.get_num_threads() == 1 and loop_threads() == threads
            with serial_torch() as inner:  # nested: still the outer caller's count
                assert inner == threads and loop_threads() == threads
            assert torch.get_num_threads() == 1 and loop_threads() == threads
        assert torch.get_num_threads() == threads and loop_threads() == threads
        with pytest.raises(RuntimeError), serial_torch():
            raise RuntimeError("boom")
        assert torch.get_num_threads() == threads and loop_threads() == threads
    finally:
        torch.set_num_threads(prev)


def test_form_factors_cast_rays_on_the_callers_threads(monkeypatch):
    """Inside form_factors torch runs on one thread, but the ray casting still splits across the caller's."""
    from torch_interreflect.geometry import raycast

    seen = []
    real = raycast._pool

    def spy(n):
        seen.append(n)
        return real(n)

    monkeypatch.setattr(raycast, "_pool", spy)
    prev = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        K = ti.form_factors(ti.scenes.cornell_box(6, light=False))
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(prev)
    assert K.info["rays"] > 0 and seen and set(seen) == {2}
    assert np.isfinite(K.to_dense().numpy()).all()


def test_only_the_compiled_path_runs_torch_serially(monkeypatch):
    """backend="torch" (and scenes off the CPU, or without numba) keep torch's threads: its quadrature is torch."""
    import contextlib

    from torch_interreflect.formfactors import quadrature

    entered = []

    @contextlib.contextmanager
    def spy():
        entered.append(True)
        yield 1

    monkeypatch.setattr(quadrature, "serial_torch", spy)
    scene = ti.scenes.v_groove(60.0, divisions=2)
    ti.form_factors(scene, backend="torch")
    assert not entered
    ti.form_factors(scene)
    assert entered == [True]
