"""Facets to images: a pinhole camera (kornia) and a pixel × facet coverage matrix.

Ray casting happens once per geometry and camera (:func:`project`): every pixel is split into ``s × s``
sub-pixels, one ray through each sub-pixel centre finds the first facet it hits (Embree), and the fraction of a
pixel's rays that hit facet ``j`` *from its reflecting side* is ``coverage[p, j]``; the fraction that escapes is
the pixel's ``background``. Rays that hit the back of a facet count for neither (an opaque, unlit back). The
result is a :class:`Projection`: a module whose sparse CSR buffer turns facet values into images,
``image = coverage @ facet_rgb``, differentiable in the facet values.

Camera conventions (kornia's :class:`~kornia.geometry.camera.PinholeCamera`, OpenCV-like): camera ``x`` to the
right of the image, ``y`` down, ``z`` forward; pixel ``(u, v)`` (column, row) has its centre at integer
coordinates and covers ``[u − ½, u + ½] × [v − ½, v + ½]``; :func:`look_at` puts the principal point at the image
centre ``((W − 1)/2, (H − 1)/2)`` and uses a vertical field of view.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from kornia.geometry.camera import PinholeCamera
from torch import Tensor, nn

from .._checks import check_count
from .._sparse import sparse_matrix
from ..errors import ShapeError, ValueRangeError
from ..geometry.scene import Scene

__all__ = ["Projection", "look_at", "project", "render_image"]


def _vec3(x: Tensor | Sequence[float], name: str) -> Tensor:
    t = torch.as_tensor(x, dtype=torch.float64).detach().cpu().reshape(-1)
    if t.numel() != 3 or not bool(torch.isfinite(t).all()):
        raise ValueRangeError(f"{name} must be a finite 3-vector (metres); got {t.tolist()}")
    return t


def _size(v: int | None, name: str) -> int:
    if v is None or isinstance(v, bool) or int(v) != v or int(v) < 1:
        raise ValueError(f"{name} must be a positive integer (pixels); got {v!r}")
    return int(v)


def look_at(
    eye: Tensor | Sequence[float],
    target: Tensor | Sequence[float],
    height: int,
    width: int,
    *,
    up: Tensor | Sequence[float] = (0.0, 1.0, 0.0),
    fov_deg: float = 40.0,
    dtype: torch.dtype = torch.float64,
) -> PinholeCamera:
    """A kornia pinhole camera at ``eye`` looking at ``target``.

    Args:
        eye: Camera centre in metres. Shape ``[3]``.
        target: A point on the optical axis in metres. Shape ``[3]``.
        height: Image height in pixels.
        width: Image width in pixels.
        up: World direction that appears up in the image (must not be parallel to the view direction).
        fov_deg: Vertical field of view in degrees, in (0, 180).
        dtype: Floating dtype of the camera's matrices.

    Returns:
        A :class:`kornia.geometry.camera.PinholeCamera` with batch size 1; ``fx = fy = (H/2) / tan(fov/2)``,
        principal point at the image centre.

    Raises:
        ValueRangeError: ``eye == target``, ``up`` parallel to the view direction, non-finite vectors.
        ValueError: bad sizes or field of view.

    Example:
        >>> from torch_interreflect.camera import look_at
        >>> cam = look_at([0, 0, -1], [0, 0, 0], 32, 48)
        >>> cam.project(torch.tensor([[0.0, 0.0, 0.0]], dtype=torch.float64)).tolist()  # image centre
        [[23.5, 15.5]]
    """
    h, w = _size(height, "height"), _size(width, "width")
    if not (isinstance(fov_deg, (int, float)) and 0.0 < float(fov_deg) < 180.0):
        raise ValueError(f"fov_deg must lie in (0, 180) degrees; got {fov_deg!r}")
    e, t, u = _vec3(eye, "eye"), _vec3(target, "target"), _vec3(up, "up")
    f = t - e
    if float(f.norm()) == 0.0:
        raise ValueRangeError(f"eye and target must differ; both are {e.tolist()}")
    f = f / f.norm()
    x = torch.linalg.cross(f, u)
    if float(x.norm()) < 1e-9 * float(u.norm()) or float(u.norm()) == 0.0:
        raise ValueRangeError(f"up {u.tolist()} must not be parallel to the view direction {f.tolist()}")
    x = x / x.norm()
    y = torch.linalg.cross(f, x)
    rot = torch.stack([x, y, f])  # rows: camera axes in world coordinates (world → camera)
    ext = torch.eye(4, dtype=torch.float64)
    ext[:3, :3] = rot
    ext[:3, 3] = -rot @ e
    focal = 0.5 * h / math.tan(math.radians(float(fov_deg)) / 2)
    intr = torch.eye(4, dtype=torch.float64)
    intr[0, 0] = intr[1, 1] = focal
    intr[0, 2], intr[1, 2] = (w - 1) / 2, (h - 1) / 2
    return PinholeCamera(
        intr[None].to(dtype),
        ext[None].to(dtype),
        torch.tensor([h], dtype=dtype),
        torch.tensor([w], dtype=dtype),
    )


def render_image(
    coverage: Tensor,
    facet_values: Tensor,
    height: int,
    width: int,
    *,
    background: Tensor | None = None,
    background_value: Tensor | float | None = None,
) -> Tensor:
    """Images from per-facet values: ``image[b, c, p] = Σ_j coverage[p, j] values[b, j, c]`` (+ background).

    Differentiable in ``facet_values`` (and ``background_value``).

    Args:
        coverage: Pixel × facet coverage, dense or sparse CSR. Shape ``[H·W, F]``.
        facet_values: Values per facet (e.g. camera RGB). Shape ``[F, C]`` or ``[B, F, C]``.
        height: ``H``.
        width: ``W``.
        background: Fraction of each pixel that sees no facet. Shape ``[H, W]``; needed with ``background_value``.
        background_value: Value of the background, a number or ``[C]`` / ``[B, C]``; none (zero) by default.

    Returns:
        Images. Shape ``[B, C, H, W]`` (``B = 1`` for ``[F, C]`` input).

    Raises:
        ShapeError: mismatched facet counts or pixel counts.

    Example:
        >>> from torch_interreflect.camera import render_image
        >>> cov = torch.tensor([[1.0, 0.0], [0.5, 0.5]])      # 2 pixels (1 × 2 image), 2 facets
        >>> render_image(cov, torch.tensor([[1.0], [3.0]]), 1, 2).flatten().tolist()
        [1.0, 2.0]
    """
    if not isinstance(facet_values, Tensor) or facet_values.ndim not in (2, 3):
        raise ShapeError(
            f"facet_values must be a tensor [F, C] or [B, F, C]; got {getattr(facet_values, 'shape', facet_values)}"
        )
    if coverage.ndim != 2 or coverage.shape[0] != height * width:
        raise ShapeError(f"coverage must be [H·W, F] = [{height * width}, F]; got {list(coverage.shape)}")
    v = facet_values if facet_values.ndim == 3 else facet_values[None]
    n_b, n_f, n_c = v.shape
    if n_f != coverage.shape[1]:
        raise ShapeError(
            f"facet_values has {n_f} facets (shape {list(facet_values.shape)}) but the coverage has "
            f"{coverage.shape[1]}"
        )
    cov = coverage.to(device=v.device, dtype=v.dtype)
    cols = v.permute(1, 0, 2).reshape(n_f, n_b * n_c)
    img = (cov @ cols).reshape(height, width, n_b, n_c).permute(2, 3, 0, 1)
    if background_value is not None:
        if background is None:
            raise ValueError("background_value needs the background mask [H, W]")
        bv = torch.as_tensor(background_value, dtype=v.dtype, device=v.device)
        bv = bv.reshape(-1, n_c, 1, 1) if bv.numel() > 1 else bv
        img = img + background.to(device=v.device, dtype=v.dtype) * bv
    return img


class Projection(nn.Module):
    """A camera's view of a scene: the pixel × facet coverage matrix and the background fraction.

    Built by :func:`project`. ``forward(facet_values)`` calls :func:`render_image`. The coverage (sparse CSR) and
    the masks are non-persistent buffers, so ``.to(device, dtype)`` moves them but they are not saved in a
    ``state_dict`` (rebuild them from the geometry).

    Attributes:
        coverage: Fraction of each pixel's sub-pixel rays that hit each facet's reflecting side. Sparse CSR
            ``[H·W, F]``; each row sums to ``1 − background − backside``.
        background: Fraction of each pixel that sees no facet. ``[H, W]``.
        facet_index: Facet hit by the most sub-pixel rays of each pixel, −1 where none (background or backs).
            ``[H, W]`` (int64).
        height, width: Image size in pixels.
        camera: The :class:`kornia.geometry.camera.PinholeCamera` used.

    Shape:
        - Input: facet values ``[F, C]`` or ``[B, F, C]``
        - Output: ``[B, C, H, W]``
    """

    coverage: Tensor
    background: Tensor
    facet_index: Tensor

    def __init__(
        self,
        coverage: Tensor,
        background: Tensor,
        facet_index: Tensor,
        camera: PinholeCamera | None = None,
        supersample: int = 1,
    ) -> None:
        super().__init__()
        if background.ndim != 2 or facet_index.shape != background.shape:
            raise ShapeError(
                f"background and facet_index must both be [H, W]; got {list(background.shape)} and "
                f"{list(facet_index.shape)}"
            )
        h, w = background.shape
        if coverage.ndim != 2 or coverage.shape[0] != h * w:
            raise ShapeError(f"coverage must be [H·W, F] = [{h * w}, F]; got {list(coverage.shape)}")
        self.height, self.width = int(h), int(w)
        self.camera = camera
        self.supersample = int(supersample)
        self.register_buffer("coverage", coverage, persistent=False)
        self.register_buffer("background", background, persistent=False)
        self.register_buffer("facet_index", facet_index, persistent=False)

    @property
    def num_facets(self) -> int:
        return int(self.coverage.shape[1])

    def pixel_counts(self) -> Tensor:
        """Pixels covered by each facet (sum of its coverage column). Shape ``[F]``."""
        ones = torch.ones(self.coverage.shape[0], 1, dtype=self.coverage.dtype, device=self.coverage.device)
        return (self.coverage.transpose(0, 1) @ ones).reshape(-1) if self.coverage.layout != torch.strided else (
            self.coverage.sum(0)
        )

    def forward(self, facet_values: Tensor, background_value: Tensor | float | None = None) -> Tensor:
        """Images ``[B, C, H, W]`` of facet values ``[F, C]`` or ``[B, F, C]``."""
        return render_image(
            self.coverage,
            facet_values,
            self.height,
            self.width,
            background=self.background,
            background_value=background_value,
        )

    def to_facets(
        self, image: Tensor, *, min_pixels: float = 0.0, method: str = "lstsq"
    ) -> tuple[Tensor, Tensor]:
        """Per-facet values from an image: the inverse of :meth:`forward` on the facets the camera sees.

        ``"lstsq"`` (default) solves ``min_v ‖coverage·v − image‖²`` over the seen facets, which recovers the facet
        values exactly from an image made by :meth:`forward` (pixels shared by several facets included); it
        uses a dense ``[H·W, F_seen]`` copy of the coverage. ``"mean"`` is the coverage-weighted mean
        ``Σ_p coverage[p, j] image[p] / Σ_p coverage[p, j]`` (biased at facet edges, cheap, robust to noise).
        Differentiable in ``image``.

        Args:
            image: ``[B, C, H, W]``, without background (``background_value=None``).
            min_pixels: Facets covering at most this many pixels get value 0 and ``seen = False``.
            method: ``"lstsq"`` or ``"mean"``.

        Returns:
            ``(values [B, F, C], seen [F] bool)``.
        """
        if image.ndim != 4 or image.shape[-2:] != (self.height, self.width):
            raise ShapeError(f"image must be [B, C, {self.height}, {self.width}]; got {list(image.shape)}")
        if method not in ("lstsq", "mean"):
            raise ValueError(f"method must be 'lstsq' or 'mean'; got {method!r}")
        n_b, n_c = image.shape[:2]
        cols = image.permute(2, 3, 0, 1).reshape(self.height * self.width, n_b * n_c)
        counts = self.pixel_counts().to(image.dtype)
        seen = counts > min_pixels
        out = torch.zeros(self.num_facets, n_b * n_c, dtype=image.dtype, device=image.device)
        if method == "lstsq":
            dense = self.coverage.to_dense().to(image.dtype)[:, seen]
            out[seen] = torch.linalg.lstsq(dense, cols).solution if int(seen.sum()) else out[seen]
        else:
            cov_t = self.coverage.to(image.dtype).transpose(0, 1)
            sums = cov_t @ cols
            out = torch.where(seen[:, None], sums / counts.clamp_min(1e-12)[:, None], out)
        return out.reshape(-1, n_b, n_c).permute(1, 0, 2), seen

    def extra_repr(self) -> str:
        return f"height={self.height}, width={self.width}, facets={self.num_facets}, supersample={self.supersample}"


def project(
    scene: Scene,
    camera: PinholeCamera | tuple[Sequence[float], Sequence[float]],
    height: int | None = None,
    width: int | None = None,
    *,
    up: Sequence[float] = (0.0, 1.0, 0.0),
    fov_deg: float = 40.0,
    supersample: int = 3,
) -> Projection:
    """Ray-cast a scene once from a pinhole camera: the pixel × facet coverage matrix of its image.

    Each pixel is split into ``supersample × supersample`` sub-pixels; the ray through each sub-pixel centre
    (kornia's ``PinholeCamera.unproject``) is traced with Embree (:class:`~torch_interreflect.raycast.RayCaster`).
    ``coverage[p, j]`` is the fraction of pixel ``p``'s rays whose first hit is the reflecting (front) side of
    facet ``j`` — an anti-aliased, area-weighted footprint, exact for facet edges on sub-pixel boundaries. Rays
    that escape make up the ``background`` fraction; rays hitting the back of a facet count for neither.

    Args:
        scene: The scene.
        camera: A kornia ``PinholeCamera`` (batch size 1; ``height``/``width`` default to its own), or a pair
            ``(eye, target)`` in metres given to :func:`look_at` with ``up`` and ``fov_deg``.
        height: Image height in pixels (required with ``(eye, target)``).
        width: Image width in pixels (required with ``(eye, target)``).
        up: See :func:`look_at`.
        fov_deg: See :func:`look_at`.
        supersample: Sub-pixels per pixel side (1 = one ray per pixel centre).

    Returns:
        A :class:`Projection` in the scene's dtype: ``projection(facet_rgb)`` gives ``[B, 3, H, W]``.

    Raises:
        ValueError: bad sizes or ``supersample``; a camera with batch size other than 1; sizes that disagree with
            the camera's.

    Example:
        >>> import torch_interreflect as ti
        >>> from torch_interreflect.camera import project
        >>> scene = ti.scenes.v_groove(90.0, divisions=2)
        >>> proj = project(scene, ([0.03, 0.03, 0.1], [0.03, 0.03, 0.0]), 16, 16, supersample=2)
        >>> proj(torch.ones(scene.num_facets, 3)).shape
        torch.Size([1, 3, 16, 16])
    """
    from ..geometry.raycast import RayCaster

    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a Scene; got {type(scene).__name__}")
    check_count(supersample, "supersample")
    s = int(supersample)
    if isinstance(camera, PinholeCamera):
        if camera.batch_size != 1:
            raise ValueError(f"camera must have batch size 1; got {camera.batch_size}")
        ch, cw = int(camera.height[0]), int(camera.width[0])
        if (height is not None and int(height) != ch) or (width is not None and int(width) != cw):
            raise ValueError(f"height/width {height}×{width} disagree with the camera's {ch}×{cw}")
        pin, h, w = camera, ch, cw
    else:
        if not (isinstance(camera, (tuple, list)) and len(camera) == 2):
            raise TypeError(f"camera must be a kornia PinholeCamera or a pair (eye, target); got {camera!r}")
        h, w = _size(height, "height"), _size(width, "width")
        pin = look_at(camera[0], camera[1], h, w, up=up, fov_deg=fov_deg)

    pin64 = PinholeCamera(
        pin.intrinsics.detach().cpu().double(),
        pin.extrinsics.detach().cpu().double(),
        pin.height.detach().cpu().double(),
        pin.width.detach().cpu().double(),
    )
    off = (torch.arange(s, dtype=torch.float64) + 0.5) / s - 0.5
    us = (torch.arange(w, dtype=torch.float64)[:, None] + off).reshape(-1)
    vs = (torch.arange(h, dtype=torch.float64)[:, None] + off).reshape(-1)
    vv, uu = torch.meshgrid(vs, us, indexing="ij")  # [H·s, W·s]
    pix = torch.stack([uu, vv], -1).reshape(1, -1, 2)
    pts = pin64.unproject(pix, torch.ones(1, pix.shape[1], 1, dtype=torch.float64))[0]  # [N, 3] at depth 1
    rot, trans = pin64.rotation_matrix[0], pin64.translation_vector[0].reshape(3)
    eye = -rot.T @ trans
    dirs = pts - eye
    hit = torch.from_numpy(RayCaster(scene).first_hit(np.broadcast_to(eye.numpy(), dirs.shape), dirs.numpy()))
    normals = scene.normals.detach().cpu().double()
    front = torch.zeros_like(hit, dtype=torch.bool)
    ok = hit >= 0
    front[ok] = (normals[hit[ok]] * dirs[ok]).sum(-1) < 0
    rows = (torch.arange(h * s)[:, None] // s * w + torch.arange(w * s)[None, :] // s).reshape(-1)
    n_f = scene.num_facets
    idx = torch.stack([rows[front], hit[front]])
    # integer counts first (exact sums), then one division: a fully covered pixel has coverage exactly 1
    coo = sparse_matrix(idx[0], idx[1], torch.ones(idx.shape[1], dtype=torch.float64), (h * w, n_f), None)
    ci = coo.indices()
    coverage = sparse_matrix(ci[0], ci[1], coo.values() / (s * s), coo.shape, scene.dtype, ordered=True)
    background = torch.bincount(rows[~ok], minlength=h * w).to(torch.float64) / (s * s)
    # dominant facet per pixel (for masks and debugging)
    dense_counts = torch.zeros(h * w, n_f + 1, dtype=torch.int32)
    tgt = torch.where(front, hit, torch.full_like(hit, n_f))
    dense_counts.index_put_((rows, tgt), torch.ones_like(rows, dtype=torch.int32), accumulate=True)
    best = dense_counts[:, :n_f].argmax(1)
    best = torch.where(dense_counts[:, :n_f].amax(1) > 0, best, torch.full_like(best, -1))
    device = scene.device
    return Projection(
        coverage.to(device),
        background.reshape(h, w).to(device=device, dtype=scene.dtype),
        best.reshape(h, w).to(device),
        camera=pin,
        supersample=s,
    )


# ------------------------------------------------------------------------------------------ image operations


