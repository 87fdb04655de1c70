"""errors.collect_warnings: one category collected, every other warning through the filters as it comes."""

from __future__ import annotations

import warnings

import pytest
import torch

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


def test_counts_are_checked_by_one_rule() -> None:
    """``_checks.check_count``: every count (samples, rays per side, strides, k) by the same rule and message."""
    import numpy as np
    import torch

    import torch_interreflect as ti
    from torch_interreflect._checks import check_count
    from torch_interreflect.errors import ValueRangeError

    assert check_count(3, "n") == 3 and check_count(np.int64(2), "n") == 2
    assert check_count(0, "n", minimum=0) == 0 and check_count(None, "n", optional=True) is None
    for bad in (0, -1, 2.5, 4.0, True, None, "3", float("nan"), torch.tensor(2)):
        with pytest.raises(ValueRangeError, match=r"n must be an integer >= 1 \(rays\); got"):
            check_count(bad, "n", note=" (rays)")
    with pytest.raises(ValueError, match="edge_supersample must be None or an integer >= 1; got 0"):
        check_count(0, "edge_supersample", optional=True)
    scene = ti.scenes.v_groove(90.0, divisions=1, dtype=torch.float64)  # the callers raise it
    with pytest.raises(ValueRangeError, match="k must be an integer >= 1"):
        scene.subdivide(0)
    with pytest.raises(ValueRangeError, match="shadow_samples must be an integer >= 1; got 0"):
        ti.lights.lit_fraction(scene, torch.tensor([0.0, 0.0, -1.0]), shadow_samples=0)
    with pytest.raises(ValueRangeError, match=r"visibility_samples must be an integer >= 1; got 1\.5"):
        ti.form_factors(scene, visibility_samples=1.5)


@pytest.mark.parametrize("shapes", [((2, 1, 3), (4, 3)), ((), (5,)), ((0, 3), (1, 3)), ((3,), (3,)),
                                    (torch.Size([2, 1]), torch.Size([1, 7])), ((1,), (0,))])
def test_broadcast_shapes_agrees_with_torch(shapes) -> None:
    from torch_interreflect._checks import broadcast_shapes

    assert broadcast_shapes(*shapes) == torch.broadcast_shapes(*shapes)
    assert type(broadcast_shapes(*shapes)) is torch.Size


def test_broadcast_shapes_that_do_not_broadcast_are_shape_errors() -> None:
    from torch_interreflect._checks import broadcast_shapes
    from torch_interreflect.errors import ShapeError

    with pytest.raises(RuntimeError):
        torch.broadcast_shapes((2, 3), (4,))
    with pytest.raises(ShapeError, match=r"shapes \[\[2, 3\], \[4\]\] do not broadcast"):
        broadcast_shapes((2, 3), (4,))
