"""Where the camera stands: :class:`View`, a small frozen (hashable) description of a pinhole view.

A :class:`View` holds what a user states about a picture (eye, target, up, vertical field of view, image size);
:meth:`View.pinhole` turns it into the kornia :class:`~kornia.geometry.camera.PinholeCamera` that
:func:`~torch_interreflect.camera.project` and :func:`~torch_interreflect.camera.gather_operator` cast rays
with, through :func:`~torch_interreflect.camera.look_at` (OpenCV-like axes: ``x`` right, ``y`` down, ``z``
forward; principal point at the image centre; vertical field of view). Being frozen and hashable, a view is a
cache key: the gather operator of a (scene, view, light) is built once.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from kornia.geometry.camera import PinholeCamera

from .._checks import check_count
from ..errors import ValueRangeError
from .projection import look_at

__all__ = ["PATTERNS", "View"]

#: Sub-pixel ray patterns of :meth:`View.rays`.
PATTERNS = ("grid", "sobol")


def _triple(v: Sequence[float] | torch.Tensor, name: str) -> tuple[float, float, float]:
    t = torch.as_tensor(v, dtype=torch.float64).detach().cpu().reshape(-1)
    if t.numel() != 3 or not bool(torch.isfinite(t).all()):
        raise ValueRangeError(f"{name} must be a finite 3-vector (metres); got {t.tolist()}")
    return (float(t[0]), float(t[1]), float(t[2]))


@dataclass(frozen=True)
class View:
    """A pinhole view of a scene: camera centre, a point it looks at, the up direction, field of view, size.

    Args:
        eye: Camera centre in metres. ``[3]``.
        target: A point on the optical axis in metres. ``[3]``.
        up: World direction that appears up in the image (default ``+z``, the scene builders' up); must not be
            parallel to ``target − eye``.
        fov_deg: Vertical field of view in degrees, in (0, 180).
        height: Image height in pixels.
        width: Image width in pixels.

    Raises:
        ValueRangeError: non-finite vectors, ``eye == target``, ``up`` parallel to the view direction.
        ValueError: sizes that are not positive integers, a field of view outside (0, 180).

    Example:
        >>> from torch_interreflect.camera import View
        >>> v = View((0.5, 0.5, 2.0), (0.5, 0.5, 0.0), up=(0, 1, 0), fov_deg=30, height=24, width=32)
        >>> v.pinhole().project(torch.tensor([[0.5, 0.5, 0.0]], dtype=torch.float64)).tolist()  # image centre
        [[15.5, 11.5]]
    """

    eye: tuple[float, float, float]
    target: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    fov_deg: float = 40.0
    height: int = 64
    width: int = 64

    def __post_init__(self) -> None:
        for name in ("eye", "target", "up"):
            object.__setattr__(self, name, _triple(getattr(self, name), name))
        for name in ("height", "width"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or int(v) != v or int(v) < 1:
                raise ValueError(f"{name} must be a positive integer (pixels); got {v!r}")
            object.__setattr__(self, name, int(v))
        f = self.fov_deg
        if isinstance(f, bool) or not isinstance(f, (int, float)) or not 0.0 < float(f) < 180.0:
            raise ValueError(f"fov_deg must lie in (0, 180) degrees; got {f!r}")
        object.__setattr__(self, "fov_deg", float(f))
        self.pinhole()  # validates eye != target and up against the view direction

    @property
    def focal(self) -> float:
        """Focal length in pixels, ``(H/2) / tan(fov/2)`` (square pixels)."""
        return 0.5 * self.height / math.tan(math.radians(self.fov_deg) / 2)

    def pinhole(self, dtype: torch.dtype = torch.float64) -> PinholeCamera:
        """The kornia pinhole camera of this view (batch size 1), from :func:`look_at`."""
        return look_at(self.eye, self.target, self.height, self.width, up=self.up, fov_deg=self.fov_deg,
                       dtype=dtype)

    def rays(self, supersample: int = 1, pixels: torch.Tensor | None = None,
             pattern: str = "grid") -> tuple[torch.Tensor, torch.Tensor]:
        """The eye and the (unnormalised) directions of the sub-pixel rays, float64.

        ``pattern="grid"``: pixel ``(u, v)`` is split into ``s × s`` sub-pixels whose centres are
        ``u − ½ + (i + ½)/s``; the rays come in row-major order of the sub-pixel grid ``[H·s, W·s]``, as in
        :func:`~torch_interreflect.camera.project`. ``"sobol"``: the ``s²`` points of a scrambled Sobol sequence
        (:class:`torch.quasirandom.SobolEngine`, seed 0), the same in every pixel. For ``s²`` a power of two these
        form a (0, m, 2)-net: each of the ``s²`` equal boxes ``2^-a × 2^-b`` (``a + b = m``) of the pixel holds one
        point, so a straight edge across the pixel is placed to ``~1/s²`` of it rather than the grid's ``~1/s``.
        With ``pixels`` (flat indices ``row · W + column``, ``[N]``), only those pixels' rays, pixel by pixel, each
        pixel's ``s²`` rays in the pattern's order.

        Returns:
            ``(eye [3], directions [H·s·W·s, 3])`` (``[N·s², 3]`` with ``pixels``) in metres (directions point at
            depth 1 along the axis).
        """
        check_count(supersample, "supersample")
        if pattern not in PATTERNS:
            raise ValueError(f"pattern must be one of {list(PATTERNS)}; got {pattern!r}")
        s, h, w = int(supersample), self.height, self.width
        pin = self.pinhole()
        off = (torch.arange(s, dtype=torch.float64) + 0.5) / s - 0.5
        if pixels is None and pattern == "grid":
            us = (torch.arange(w, dtype=torch.float64)[:, None] + off).reshape(-1)
            vs = (torch.arange(h, dtype=torch.float64)[:, None] + off).reshape(-1)
            vv, uu = torch.meshgrid(vs, us, indexing="ij")
        else:
            p = torch.arange(h * w) if pixels is None else torch.as_tensor(pixels)
            if p.dtype.is_floating_point or p.dtype.is_complex or p.dtype == torch.bool:
                raise TypeError(f"pixels must be integer flat indices; got dtype {p.dtype}")
            p = p.to(torch.int64).reshape(-1)
            if p.numel() and (int(p.min()) < 0 or int(p.max()) >= h * w):
                raise ValueError(f"pixels must be flat indices in [0, {h * w}); got {int(p.min())}..{int(p.max())}")
            if pattern == "sobol":
                q = torch.quasirandom.SobolEngine(2, scramble=True, seed=0).draw(s * s, dtype=torch.float64) - 0.5
                du, dv = q[:, 0], q[:, 1]
            else:
                dv, du = torch.meshgrid(off, off, indexing="ij")
            vv = (p // w).to(torch.float64)[:, None] + dv.reshape(1, -1)
            uu = (p % w).to(torch.float64)[:, None] + du.reshape(1, -1)
        pix = torch.stack([uu, vv], -1).reshape(1, -1, 2)
        pts = pin.unproject(pix, torch.ones(1, pix.shape[1], 1, dtype=torch.float64))[0]
        eye = torch.tensor(self.eye, dtype=torch.float64)
        return eye, pts - eye
