"""``unique_rows`` against ``torch.unique(dim=)``: the same ids, counts and unique rows."""

import pytest
import torch

from torch_interreflect._unique import MAX_WIDTH, unique_rows


def _expect(x: torch.Tensor, dim: int) -> tuple[torch.Tensor, ...]:
    return torch.unique(x, dim=dim, return_inverse=True, return_counts=True)


@pytest.mark.parametrize("dtype", [torch.int64, torch.float32, torch.float64])
@pytest.mark.parametrize("width", [1, 2, 3, 6])
def test_rows_match_torch_unique(dtype: torch.dtype, width: int) -> None:
    gen = torch.Generator().manual_seed(width)
    x = torch.randint(-3, 4, (500, width), generator=gen).to(dtype)  # many repeated rows, negative values
    for got, want in zip(unique_rows(x), _expect(x, 0), strict=True):
        assert torch.equal(got, want)


def test_columns_match_torch_unique() -> None:
    gen = torch.Generator().manual_seed(1)
    x = torch.randint(0, 3, (2, 300), generator=gen)
    for got, want in zip(unique_rows(x, dim=1), _expect(x, 1), strict=True):
        assert torch.equal(got, want)


def test_signed_zero_is_one_value() -> None:
    x = torch.tensor([[0.0, 1.0], [-0.0, 1.0], [0.0, -1.0]], dtype=torch.float64)
    uniq, inverse, counts = unique_rows(x)
    assert inverse.tolist() == [1, 1, 0] and counts.tolist() == [1, 2]
    for got, want in zip((uniq, inverse, counts), _expect(x, 0), strict=True):
        assert torch.equal(got, want)


def test_large_values_do_not_overflow() -> None:
    # ranks are folded column by column, so the keys stay below n² whatever the values
    x = torch.tensor([[2**62, -(2**62)], [2**62, 2**61], [-(2**62), 0], [2**62, -(2**62)]])
    for got, want in zip(unique_rows(x), _expect(x, 0), strict=True):
        assert torch.equal(got, want)


def test_wide_rows_and_empty_input_fall_back() -> None:
    wide = torch.randint(0, 2, (40, MAX_WIDTH + 1), generator=torch.Generator().manual_seed(2))
    for got, want in zip(unique_rows(wide), _expect(wide, 0), strict=True):
        assert torch.equal(got, want)
    empty = torch.zeros(0, 3)
    for got, want in zip(unique_rows(empty), _expect(empty, 0), strict=True):
        assert got.shape == want.shape and got.dtype == want.dtype
