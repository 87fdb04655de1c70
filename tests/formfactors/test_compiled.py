"""The compiled loops' on-disk cache follows every one of their sources (:func:`refresh_cache`): numba itself checks
only the file that defines a kernel, so an edit of a module whose functions a kernel inlines kept the old code."""

import os
from pathlib import Path

import numpy as np
import pytest
import torch

import torch_interreflect as ti
from torch_interreflect.formfactors import compiled
from torch_interreflect.formfactors.compiled import loops, refresh_cache

HERE = Path(compiled.__file__).resolve().parent


def _tree(tmp_path: Path) -> tuple[Path, Path]:
    src, cache = tmp_path / "pkg", tmp_path / "pkg" / "__pycache__"
    cache.mkdir(parents=True)
    (src / "_numba_a.py").write_text("A = 1\n")
    (src / "_numba_b.py").write_text("B = 2\n")
    (src / "other.py").write_text("C = 3\n")
    return src, cache


def _cached(cache: Path) -> list[str]:
    for name in ("_numba_a.f-10.py311.nbi", "_numba_a.f-10.py311.1.nbc", "_numba_b.g-3.py311.nbi", "other.h.nbi"):
        (cache / name).write_bytes(b"x")
    return sorted(p.name for p in cache.iterdir() if p.suffix in (".nbi", ".nbc"))


def test_cache_dropped_when_any_source_changes(tmp_path):
    src, cache = _tree(tmp_path)
    _cached(cache)
    assert refresh_cache(src, cache)  # no record: kernels of unknown sources are dropped
    assert sorted(p.name for p in cache.iterdir() if p.suffix in (".nbi", ".nbc")) == ["other.h.nbi"]
    kept = _cached(cache)
    assert not refresh_cache(src, cache)  # same sources: the cache stays
    assert sorted(p.name for p in cache.iterdir() if p.suffix in (".nbi", ".nbc")) == kept
    (src / "_numba_b.py").write_text("B = 3\n")  # the inlined helper edited, not the kernel's own file
    assert refresh_cache(src, cache)
    assert sorted(p.name for p in cache.iterdir() if p.suffix in (".nbi", ".nbc")) == ["other.h.nbi"]
    (src / "other.py").write_text("C = 4\n")  # not a compiled module: no effect
    _cached(cache)
    assert not refresh_cache(src, cache)


def test_cache_without_its_folder_is_left_alone(tmp_path):
    src, cache = _tree(tmp_path)
    cache.rmdir()
    assert not refresh_cache(src, cache)
    assert not cache.exists()


@pytest.mark.skipif(loops("moments") is None or not os.access(HERE, os.W_OK),
                    reason="compiled loops disabled, or a read-only install (numba caches elsewhere)")
def test_record_matches_the_installed_sources():
    """After the first import the record beside the cached kernels is the digest of today's sources, so a kernel
    loaded from the cache was compiled from them (where the package folder is writable)."""
    assert not refresh_cache(HERE, HERE / "__pycache__") or not (HERE / "__pycache__").is_dir()
    s = ti.scenes.v_groove(90.0, size=(1.0, 1.0), divisions=1, dtype=torch.float64)
    G = ti.formfactors.moment_form_factors(s, degree=2)
    np.testing.assert_allclose(float(G.matrix[0, 6]), 0.2000438, atol=1e-7)  # F_01, two unit squares at 90°


def test_dealt_is_a_permutation_dealing_in_turn():
    from torch_interreflect._threads import compiled_work
    from torch_interreflect.formfactors.compiled import dealt

    items = np.arange(7) * 10
    torch_threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        assert np.array_equal(dealt(items), items)
        torch.set_num_threads(2)
        with compiled_work():  # the caller's 2 threads, torch's glue on one
            got = dealt(items)
    finally:
        torch.set_num_threads(torch_threads)
    if loops("moments") is not None:
        import numba

        if numba.config.NUMBA_NUM_THREADS >= 2:
            assert got.tolist() == [0, 20, 40, 60, 10, 30, 50]


@pytest.mark.skipif(loops("moments") is None, reason="compiled loops disabled")
def test_moments_the_same_bits_on_any_thread_count():
    """The pairs are dealt to the threads in another order per thread count; each pair's sums and rays (jitter keyed
    by the pair) do not depend on it."""
    from torch_interreflect.formfactors.moments import resample_visibility

    scene = ti.geometry.split_at_contacts(ti.scenes.cornell_box(light=False, divisions=1))[0]
    torch_threads = torch.get_num_threads()
    out = []
    try:
        for n in (1, 2):
            torch.set_num_threads(n)
            K = ti.formfactors.moment_form_factors(scene, 2, quadrature_tol=1e-3)
            out.append((K.matrix, resample_visibility(K, seed=1).matrix, K.info["rays"]))
    finally:
        torch.set_num_threads(torch_threads)
    assert out[0][2] == out[1][2] > 0
    assert torch.equal(out[0][0], out[1][0]) and torch.equal(out[0][1], out[1][1])
