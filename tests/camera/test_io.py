"""save_image: 8-bit sRGB previews and 16-bit linear PNGs, read back with kornia.io."""

from __future__ import annotations

from pathlib import Path

import kornia
import pytest
import torch

from torch_interreflect.camera import save_image, to_srgb
from torch_interreflect.errors import ShapeError, ValueRangeError

UNCHANGED = kornia.io.ImageLoadType.UNCHANGED


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_linear_16bit_round_trip(tmp_path: Path, dtype: torch.dtype) -> None:
    img = torch.rand(3, 5, 7, dtype=dtype, generator=torch.Generator().manual_seed(0))
    p = save_image(tmp_path / "a" / "lin.png", img, exposure=0.5, srgb=False)
    back = kornia.io.load_image(p, UNCHANGED)
    assert back.dtype == torch.uint16 and back.shape == (3, 5, 7)
    assert torch.allclose(back.to(torch.float64) / 65535, (0.5 * img).double(), atol=0.5 / 65535 + 1e-9)


def test_srgb_8bit_preview(tmp_path: Path) -> None:
    img = torch.linspace(0, 2, 3 * 4 * 4).reshape(3, 4, 4)
    p = save_image(tmp_path / "prev.png", img[None])  # [1, 3, H, W] accepted
    back = kornia.io.load_image(p, UNCHANGED)
    expected = (to_srgb(img[None].double())[0] * 255).round()
    assert back.dtype == torch.uint8 and torch.equal(back.double(), expected)
    assert int(back.max()) == 255  # clipped above 1


def test_grey(tmp_path: Path) -> None:
    back = kornia.io.load_image(save_image(tmp_path / "g.png", torch.full((4, 6), 0.25), srgb=False), UNCHANGED)
    assert back.shape == (1, 4, 6) and int(back[0, 0, 0]) == round(0.25 * 65535)


def test_bad_input(tmp_path: Path) -> None:
    with pytest.raises(ShapeError):
        save_image(tmp_path / "x.png", torch.zeros(2, 3, 4, 4))
    with pytest.raises(ValueRangeError, match="finite"):
        save_image(tmp_path / "x.png", torch.full((3, 2, 2), float("nan")))
    with pytest.raises(ValueRangeError, match="exposure"):
        save_image(tmp_path / "x.png", torch.zeros(3, 2, 2), exposure=0)
