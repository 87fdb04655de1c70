"""errors.collect_warnings: one category collected, every other warning through the filters as it comes."""

from __future__ import annotations

import warnings

import pytest

from torch_interreflect.errors import AccuracyWarning, ConvergenceWarning, collect_warnings


def _warn_both(k: int) -> None:
    warnings.warn(f"bound {k} above tol", AccuracyWarning, stacklevel=1)
    warnings.warn("the same text each time", ConvergenceWarning, stacklevel=1)


def test_the_category_is_collected_and_the_rest_keeps_its_filters() -> None:
    """Five passes: the collected category five times; another warning under the "default" action (once per
    location) shown once, as without the block."""
    with warnings.catch_warnings(record=True) as shown:
        warnings.simplefilter("default")
        with collect_warnings(AccuracyWarning) as got:
            for k in range(5):
                _warn_both(k)
    assert got == [f"bound {k} above tol" for k in range(5)]
    assert [w.category for w in shown] == [ConvergenceWarning]


def test_other_warnings_survive_an_error_in_the_block_and_an_error_filter_applies() -> None:
    with warnings.catch_warnings(record=True) as shown:
        warnings.simplefilter("always")
        with pytest.raises(RuntimeError), collect_warnings(AccuracyWarning):
            _warn_both(0)
            raise RuntimeError("later")
    assert [w.category for w in shown] == [ConvergenceWarning]
    with warnings.catch_warnings():
        warnings.simplefilter("error", ConvergenceWarning)
        with pytest.raises(ConvergenceWarning), collect_warnings(AccuracyWarning) as got:
            _warn_both(1)
    assert got == ["bound 1 above tol"]
