"""solve and the Interreflection layer on every device the `device` fixture offers (CUDA cases skip without a GPU;
`pytest --device cuda` runs them alone): results equal the CPU float64 answer, and stay on the inputs' device."""

from __future__ import annotations

import pytest
import torch

import torch_interreflect as ti
from tests.oracles import random_reciprocal
from torch_interreflect.layers import Interreflection


@pytest.mark.parametrize("method", ["dense", "cg", "neumann"])
def test_solve_on_device(device: torch.device, dtype: torch.dtype, method: str) -> None:
    K64 = random_reciprocal(40, scale=0.9)
    g = torch.Generator().manual_seed(3)
    r = torch.rand(2, 40, 5, generator=g, dtype=torch.float64) * 0.9
    e0 = torch.rand(40, 5, generator=g, dtype=torch.float64)
    ref = ti.solve(K64, r, e0, method="dense")
    K = ti.FormFactors(K64.matrix.to(device=device, dtype=dtype), K64.areas.to(device=device, dtype=dtype))
    solve_tol = 1e-6 if dtype == torch.float32 else 1e-11
    E = ti.solve(K, r.to(device, dtype), e0.to(device, dtype), method=method, tol=solve_tol)
    assert E.device.type == device.type and E.dtype == dtype and E.shape == ref.shape
    tol = 1e-5 if dtype == torch.float32 else 1e-9
    torch.testing.assert_close(E.cpu().double(), ref, rtol=tol, atol=tol)


def test_solve_device_mismatch_is_an_error(device: torch.device) -> None:
    if device.type == "cpu":
        pytest.skip("needs a second device")
    K = random_reciprocal(8)
    with pytest.raises(ti.errors.DeviceError, match="cpu"):
        ti.solve(K, torch.full((8,), 0.5, device=device, dtype=torch.float64), torch.ones(8, 2, dtype=torch.float64))


def test_layer_on_device(device: torch.device, dtype: torch.dtype) -> None:
    wl = ti.spectral.wavelengths(dtype=dtype)
    scene = ti.scenes.v_groove(60.0, divisions=3, dtype=dtype)
    layer = Interreflection(scene, wl, "Nikon 5100 (NPL)")
    r = torch.full((2, scene.num_facets, wl.numel()), 0.6, dtype=dtype)
    S = ti.spectral.illuminant("D65", wl)
    ref = layer(r, S)
    moved = layer.to(device)
    out = moved(r.to(device), S.to(device))
    assert out.device.type == device.type and out.dtype == dtype and out.shape == (2, scene.num_facets, 3)
    tol = 1e-5 if dtype == torch.float32 else 1e-10
    torch.testing.assert_close(out.cpu(), ref, rtol=tol, atol=tol * float(ref.abs().max()))
