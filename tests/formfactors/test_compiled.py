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
