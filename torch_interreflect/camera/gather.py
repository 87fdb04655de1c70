"""Per-pixel shading by final gather: irradiance varies inside a facet, as in a path tracer's image.

For every primary hit point ``x`` of a view, ``E(x) = g0(x) S + Σ_j F(x → j) V(x, j) B_j`` with ``B = R E`` the
solved facets' radiosity, ``F(x → j)`` the exact point-to-polygon form factor (Lambert's contour formula, ``j``
clipped to the tangent plane of ``x``), ``V(x, j)`` the kernel-weighted visible fraction of ``j`` from ``x`` (Embree
rays to ``samples²`` jittered stratified points on ``j``, only for pairs a third facet could block) and ``g0(x) S``
the direct light at ``x`` itself (``S`` the light's spectrum): ``"uniform"`` ``g0 = 1``; a sun of direction ``d``
``max(0, n·(−d))`` times a shadow ray per sub-pixel ray; ``"sky"`` ``π (1 − Σ_j |F(x → j)| V(x, j))`` over every
facet, front or back; an area light (material name or mask) ``π Σ_{j ∈ light} F(x → j) V(x, j)``; a factor ``g [F]``
``g`` of the hit facet. The radiance is ``r(x) E(x) / π`` with ``r`` the hit facet's reflectance.

Sub-pixel rays (``s × s`` per pixel, as :func:`~torch_interreflect.camera.project`) are grouped into *fragments*
(pixel, hit facet): the gather is evaluated once per fragment, at the mean of its hit points, weighted by its share
of the pixel's rays. The geometry (the ``[fragments, facets]`` gather matrix, ``g0``, the coverage) is built once
per (scene, view, light) by :func:`gather_operator` and cached; the image is linear and differentiable in ``B`` and
``S`` (so in reflectance and illuminant through the solve).
"""

from __future__ import annotations

import math
import time
import warnings
from collections import OrderedDict
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from ..errors import ShapeError
from ..formfactors.fused import point_sums
from ..formfactors.visibility import blocker_candidates
from ..geometry._polygon import bilinear, clip_polygons, facing_others, plane_eps
from ..geometry.raycast import RayCaster
from ..geometry.scene import Scene
from .sensor import Camera
from .view import View

__all__ = ["Gather", "gather_operator", "gathered_image", "gathered_radiance", "point_form_factors", "render_view"]

#: Largest number of (point, facet) pairs evaluated at once (memory ~ 1 kB per pair).
PAIR_CHUNK = 1 << 16
#: Most operators kept by the cache of :func:`gather_operator`.
CACHE_SIZE = 8
_CACHE: OrderedDict[tuple, Gather] = OrderedDict()


def _sparse(rows: Tensor, cols: Tensor, vals: Tensor, shape: tuple[int, int], dtype: torch.dtype | None,
            ordered: bool = False) -> Tensor:
    """COO (coalesced, float64 sums) → CSR in ``dtype``; ``dtype=None`` keeps the coalesced COO.

    ``ordered``: the ``(row, col)`` pairs are already unique and sorted row-major (no sort needed).
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # "sparse CSR support is in beta"
        coo = torch.sparse_coo_tensor(torch.stack([rows, cols]), vals, shape, is_coalesced=ordered)
        coo = coo if ordered else coo.coalesce()
        return coo if dtype is None else coo.to_sparse_csr().to(dtype)


# ------------------------------------------------------------------------------------------- point kernel
def _real_vertices(poly: Tensor, eps: float) -> Tensor:
    """Number of leading vertices of padded polygons ``[P, K, 3]`` before the padding (copies of vertex 0)."""
    same = (poly - poly[:, :1]).norm(dim=-1) <= eps
    same[:, 0] = False
    idx = torch.arange(poly.shape[1]).expand_as(same)
    return torch.where(same, idx, torch.full_like(idx, poly.shape[1])).amin(1)


def _target_samples(corners: Tensor, n: int, gen: torch.Generator) -> tuple[Tensor, Tensor]:
    """Jittered stratified points ``[F, n², 3]`` and their area weights ``[F, n²]`` on every facet (bilinear map)."""
    F = corners.shape[0]
    cells = torch.arange(n, dtype=torch.float64)
    u = (cells.repeat_interleave(n)[None] + torch.rand(F, n * n, dtype=torch.float64, generator=gen)) / n
    v = (cells.repeat(n)[None] + torch.rand(F, n * n, dtype=torch.float64, generator=gen)) / n
    y, jac = bilinear(corners, u, v)
    return y, jac / (n * n)


def _visibility(caster: RayCaster, x: Tensor, nx: Tensor, y: Tensor, w: Tensor, ny: Tensor) -> Tensor:
    """Kernel-weighted visible fraction ``[c]`` of targets sampled at ``y [c, Q, 3]`` (area weights ``w [c, Q]``,
    normals ``ny [c, 3]``) from points ``x [c, 3]`` (normals ``nx``), float32 relative to the caster's origin.

    Each sample is weighted by ``cos θ_x |cos θ_y| w / |x − y|²`` (either side of the target) and gets one Embree
    occlusion ray.
    """
    r = y - x[:, None, :]
    d2 = (r * r).sum(-1).clamp_min(1e-30)
    length = d2.sqrt()
    direction = r / length[..., None]
    k = (direction @ nx[:, :, None])[..., 0].clamp_min(0) * (direction @ ny[:, :, None])[..., 0].abs() * w / d2
    origin = x[:, None, :] + caster.eps * direction
    blocked = torch.from_numpy(
        caster.occluded(origin.reshape(-1, 3).numpy(), direction.reshape(-1, 3).numpy(),
                        (length - 2 * caster.eps).reshape(-1).numpy())
    ).reshape(k.shape)
    den = k.sum(-1)
    return torch.where(den > 0, (k * ~blocked).sum(-1) / den.clamp_min(1e-30), torch.ones_like(den)).double()


def point_form_factors(
    scene: Scene,
    points: Tensor,
    facet: Tensor,
    *,
    samples: int = 4,
    seed: int = 0,
    caster: RayCaster | None = None,
) -> tuple[Tensor, Tensor, dict[str, Any]]:
    """Exact point-to-facet form factors with occlusion, from points lying on facets of the scene.

    ``F(x → j)`` by Lambert's contour formula (facet ``j`` clipped to the tangent plane of ``x``), times the
    kernel-weighted visible fraction ``V(x, j)`` from ``samples²`` jittered stratified Embree rays, cast only for
    facet pairs that a third facet could block (:func:`~torch_interreflect.formfactors.visibility.blocker_candidates`).

    Args:
        scene: The scene.
        points: Points in metres, each on (or just above) the reflecting side of its facet. Shape ``[P, 3]``.
        facet: The facet of each point (its normal is the point's normal). Shape ``[P]`` (int64).
        samples: Visibility rays per side of the target facet (``samples²`` rays per blockable pair).
        seed: Seed of the jitter (the result is deterministic for a given seed).
        caster: A :class:`~torch_interreflect.geometry.raycast.RayCaster` of the scene to reuse.

    Returns:
        ``(factors, covered, info)``: ``factors`` sparse COO ``[P, F]`` float64 (CPU) of ``F(x → j) V(x, j)`` over
        the facets whose reflecting side ``x`` sees; ``covered [P]`` float64, the part of the cosine-weighted
        hemisphere of each point that sees any facet, front or back (the sky sees ``1 − covered``); ``info`` with
        ``pairs``, ``rays`` and ``seconds``.

    Example:
        >>> import torch, torch_interreflect as ti
        >>> from torch_interreflect.camera import point_form_factors
        >>> sq = torch.tensor([[[-.5, -.5, 0.], [.5, -.5, 0.], [.5, .5, 0.], [-.5, .5, 0.]],      # floor, up
        ...                    [[-.5, -.5, 1.], [-.5, .5, 1.], [.5, .5, 1.], [.5, -.5, 1.]]],     # ceiling, down
        ...                   dtype=torch.float64)
        >>> f, covered, _ = point_form_factors(ti.Scene.from_polygons(sq), torch.zeros(1, 3), torch.tensor([0]))
        >>> round(float(f.to_dense()[0, 1]), 7), round(float(covered[0]), 7)
        (0.2394565, 0.2394565)
    """
    t0 = time.perf_counter()
    sc = scene.to(torch.float64).to("cpu")
    x = torch.as_tensor(points, dtype=torch.float64).detach().cpu().reshape(-1, 3)
    h = torch.as_tensor(facet, dtype=torch.int64).cpu().reshape(-1)
    if h.shape[0] != x.shape[0]:
        raise ShapeError(f"points [P, 3] and facet [P] must agree; got {list(x.shape)} and {list(h.shape)}")
    if h.numel() and (int(h.min()) < 0 or int(h.max()) >= sc.num_facets):
        raise ShapeError(f"facet indices must lie in [0, {sc.num_facets}); got [{int(h.min())}, {int(h.max())}]")
    if isinstance(samples, bool) or int(samples) < 1:
        raise ValueError(f"samples must be an integer >= 1 (rays per side of a target facet); got {samples!r}")
    eps = plane_eps(scene)
    front = facing_others(scene)  # [F, F]: some corner of j strictly in front of i's plane
    fi, fj = torch.nonzero(front, as_tuple=True)
    need = blocker_candidates(sc, fi, fj, eps) if fi.numel() else torch.zeros(0, dtype=torch.bool)
    # every point of facet i has i's tangent plane: clip each target once per facet pair, not per point
    cpoly = clip_polygons(sc.corners[fj], sc.centroids[fi], sc.normals[fi], eps)
    cpoly = cpoly[:, : max(3, int(_real_vertices(cpoly, eps).max()) if fi.numel() else 3)]
    caster = caster if caster is not None else RayCaster(sc)
    gen = torch.Generator().manual_seed(int(seed))
    o = torch.as_tensor(caster.origin)
    ys, ws = _target_samples(sc.corners, int(samples), gen)
    ys, ws, nf, xf = (ys - o).float(), ws.float(), sc.normals.float(), (x - o).float()
    # pairs (point, facet in front of its facet), point by point; facet pairs (fi, fj) are row-major, so the pairs
    # of facet i are fi's run starting at first[i]
    per_facet = front.sum(1)
    first = torch.cumsum(per_facet, 0) - per_facet
    counts = per_facet[h]
    pi = torch.repeat_interleave(torch.arange(x.shape[0]), counts)
    start = torch.cumsum(counts, 0) - counts
    pid = first[h][pi] + torch.arange(pi.numel()) - start[pi]
    pj = fj[pid]
    vals, in_front = point_sums(x, sc.normals[h], pi, cpoly, pid, (sc.centroids[fj], sc.normals[fj]))
    blocked = torch.nonzero(need[pid] & (vals != 0)).reshape(-1)
    for s in range(0, blocked.numel(), PAIR_CHUNK):
        k = blocked[s : s + PAIR_CHUNK]
        a, t = pi[k], pj[k]
        vals[k] = vals[k] * _visibility(caster, xf[a], nf[h[a]], ys[t], ws[t], nf[t])
    rays = int(blocked.numel()) * int(samples) ** 2
    covered = torch.zeros(x.shape[0], dtype=torch.float64).index_add_(0, pi, vals.abs())
    keep = in_front & (vals > 0)
    # pairs run point by point, facets ascending within a point: already coalesced
    factors = _sparse(pi[keep], pj[keep], vals[keep], (x.shape[0], sc.num_facets), None, ordered=True)
    return factors, covered, {"pairs": int(pi.numel()), "rays": rays, "seconds": time.perf_counter() - t0}


# ------------------------------------------------------------------------------------------- fragments
def _primary(scene: Scene, view: View, s: int, caster: RayCaster) -> dict[str, Tensor]:
    """Sub-pixel rays → fragments (pixel, front-hit facet): facet, pixel, ray count, mean hit point, per-ray data."""
    sc = scene.to(torch.float64).to("cpu")
    eye, dirs = view.rays(s)
    hit = torch.from_numpy(caster.first_hit(np.broadcast_to(eye.numpy(), dirs.shape), dirs.numpy()))
    ok = hit >= 0
    hc = hit.clamp_min(0)
    nd = (sc.normals[hc] * dirs).sum(-1)
    front = ok & (nd < 0)
    t = ((sc.centroids[hc] - eye) * sc.normals[hc]).sum(-1) / torch.where(nd != 0, nd, torch.ones_like(nd))
    pts = eye + t[:, None] * dirs
    h, w = view.height, view.width
    rows = (torch.arange(h * s)[:, None] // s * w + torch.arange(w * s)[None, :] // s).reshape(-1)
    F = sc.num_facets
    key = rows[front] * F + hit[front]
    uniq, inv = torch.unique(key, return_inverse=True)
    count = torch.bincount(inv, minlength=uniq.numel()).to(torch.float64)
    centre = torch.zeros(uniq.numel(), 3, dtype=torch.float64).index_add_(0, inv, pts[front]) / count[:, None]
    background = torch.bincount(rows[~ok], minlength=h * w).to(torch.float64) / (s * s)
    return {"pixel": uniq // F, "facet": uniq % F, "weight": count / (s * s), "centre": centre,
            "background": background.reshape(h, w), "ray_fragment": inv, "ray_point": pts[front]}


def _coarse(frag: dict[str, Tensor], height: int, width: int, num_facets: int,
            stride: int) -> tuple[Tensor, Tensor, Tensor]:
    """Gather points every ``stride`` pixels, and the bilinear weights that carry their values to the fragments.

    A coarse fragment is (block of ``stride × stride`` pixels, facet), at the mean of its rays' hit points. Each
    fragment takes the bilinear weights of the four nearest block centres (pixel units) whose coarse fragment lies
    on the same facet, renormalised; its own block is always among them.

    Returns:
        ``(centres [Kc, 3], facets [Kc], weights)``: ``weights`` sparse COO ``[K, Kc]`` float64, rows summing to 1.
    """
    F, st = num_facets, int(stride)
    wc, hc = -(-width // st), -(-height // st)
    pix = frag["pixel"]
    py, px = pix // width, pix % width
    ray_frag = frag["ray_fragment"]
    ray_key = ((py[ray_frag] // st) * wc + px[ray_frag] // st) * F + frag["facet"][ray_frag]
    keys, inv = torch.unique(ray_key, return_inverse=True)
    count = torch.bincount(inv, minlength=keys.numel()).to(torch.float64)
    centres = torch.zeros(keys.numel(), 3, dtype=torch.float64).index_add_(0, inv, frag["ray_point"]) / count[:, None]
    cy, cx = (py.double() + 0.5) / st - 0.5, (px.double() + 0.5) / st - 0.5
    y0, x0 = cy.floor().long(), cx.floor().long()
    rows, cols, vals = [], [], []
    for dy in (0, 1):
        for dx in (0, 1):
            yy, xx = y0 + dy, x0 + dx
            w = (cy - y0 if dy else 1 - (cy - y0)) * (cx - x0 if dx else 1 - (cx - x0))
            key = (yy.clamp(0, hc - 1) * wc + xx.clamp(0, wc - 1)) * F + frag["facet"]
            at = torch.searchsorted(keys, key).clamp_max(keys.numel() - 1)
            ok = (yy >= 0) & (yy < hc) & (xx >= 0) & (xx < wc) & (keys[at] == key) & (w > 0)
            rows.append(torch.nonzero(ok).reshape(-1))
            cols.append(at[ok])
            vals.append(w[ok])
    r, c, v = torch.cat(rows), torch.cat(cols), torch.cat(vals)
    v = v / torch.zeros(pix.numel(), dtype=torch.float64).index_add_(0, r, v)[r]
    weights = torch.sparse_coo_tensor(torch.stack([r, c]), v, (pix.numel(), keys.numel())).coalesce()
    return centres, keys % F, weights


def _light_key(light: Any) -> Any:
    if isinstance(light, str):
        return light
    t = torch.as_tensor(light).detach().cpu()
    return (str(t.dtype), tuple(t.shape), t.numpy().tobytes())


def _direct(scene: Scene, light: Any, frag: dict[str, Tensor], caster: RayCaster, covered: Tensor | None,
            factors: Tensor | None) -> Tensor:
    """``g0`` per fragment (float64) for the light (see the module docstring)."""
    h = frag["facet"]
    if isinstance(light, str) and light == "uniform":
        return torch.ones(h.numel(), dtype=torch.float64)
    if isinstance(light, str) and light == "sky":
        return math.pi * (1.0 - covered).clamp_min(0.0)
    sc = scene.to(torch.float64).to("cpu")
    if isinstance(light, str):
        if scene.material_names is None or light not in scene.material_names:
            raise ValueError(
                f"light must be 'uniform', 'sky', a direction [3], a facet mask [F], a tensor [F] or a material name "
                f"of the scene {list(scene.material_names or [])}; got {light!r}"
            )
        light = (scene.material == scene.material_names.index(light)).cpu()
    t = torch.as_tensor(light).detach().cpu()
    F = scene.num_facets
    if t.dtype == torch.bool:
        if t.shape != (F,):
            raise ShapeError(f"an area-light mask must have shape [{F}] (one flag per facet); got {list(t.shape)}")
        return math.pi * torch.sparse.mm(factors, t.to(torch.float64)[:, None])[:, 0]
    if t.numel() == 3 and t.ndim == 1 and F != 3:
        d = t.to(torch.float64) / t.to(torch.float64).norm()
        ray_h = h[frag["ray_fragment"]]
        cos = (-(sc.normals[ray_h] @ d)).clamp_min(0)
        lit = cos > 0
        free = torch.zeros_like(cos)
        if bool(lit.any()):
            pts = frag["ray_point"][lit] + caster.eps * sc.normals[ray_h[lit]]
            escaped = caster.first_hit(pts.numpy(), (-d).expand(pts.shape[0], 3).numpy()) < 0
            free[lit] = torch.from_numpy(escaped).to(torch.float64)
        per_ray = cos * free
        n = torch.bincount(frag["ray_fragment"], minlength=h.numel()).to(torch.float64)
        return torch.zeros(h.numel(), dtype=torch.float64).index_add_(0, frag["ray_fragment"], per_ray) / n
    if not t.is_floating_point() or t.shape != (F,):
        raise ShapeError(f"light as a tensor must be a direction [3], a mask [F = {F}] or a factor [F]; got "
                         f"{list(t.shape)} ({t.dtype})")
    return t.to(torch.float64)[h]


# ------------------------------------------------------------------------------------------- the operator
class Gather(nn.Module):
    """The geometry of a gathered view: built by :func:`gather_operator`, used by :func:`gathered_radiance`.

    ``K`` fragments (one per pixel and front-hit facet). Buffers are non-persistent (rebuild from the geometry).

    Attributes:
        pixel_fragments: Share of each pixel's sub-pixel rays in each fragment. Sparse CSR ``[H·W, K]``.
        coverage: The same per facet (what :func:`~torch_interreflect.camera.project` gives). Sparse CSR
            ``[H·W, F]``; with ``shading="flat"`` the image is ``coverage @ facet values``.
        fragment_facet: The facet of each fragment. ``[K]`` int64.
        gather: ``F(x_k → j) V(x_k, j)`` at each fragment's mean hit point. Sparse CSR ``[K, F]`` (``None`` when
            built for flat shading only).
        direct: ``g0`` of the light at each fragment (see the module docstring). ``[K]`` (``None`` likewise).
        open_sky: ``1 − Σ_j |F(x_k → j)| V(x_k, j)``, the cosine-weighted part of each fragment's hemisphere that
            sees no facet (``g0`` of a uniform sky is ``π`` times it). ``[K]`` (``None`` likewise).
        background: Fraction of each pixel that sees no facet. ``[H, W]``.
        view: The :class:`~torch_interreflect.camera.View`; ``supersample``, ``samples``: the settings.
        info: ``pairs``, ``rays`` and ``seconds`` (per stage) of the build.
    """

    def __init__(self, view: View, frag: dict[str, Tensor], num_facets: int, dtype: torch.dtype,
                 device: torch.device, supersample: int, samples: int) -> None:
        super().__init__()
        self.view, self.supersample, self.samples = view, int(supersample), int(samples)
        self.height, self.width, self.num_facets = view.height, view.width, int(num_facets)
        K = frag["facet"].numel()
        p, w = frag["pixel"], frag["weight"]
        # fragments are sorted by (pixel, facet) and unique (torch.unique of pixel · F + facet)
        pf = _sparse(p, torch.arange(K), w, (self.height * self.width, K), dtype, ordered=True)
        cov = _sparse(p, frag["facet"], w, (self.height * self.width, self.num_facets), dtype, ordered=True)
        self.register_buffer("pixel_fragments", pf.to(device), persistent=False)
        self.register_buffer("coverage", cov.to(device), persistent=False)
        self.register_buffer("fragment_facet", frag["facet"].to(device), persistent=False)
        self.register_buffer("background", frag["background"].to(device=device, dtype=dtype), persistent=False)
        self.register_buffer("gather", None, persistent=False)
        self.register_buffer("direct", None, persistent=False)
        self.register_buffer("open_sky", None, persistent=False)
        self.info: dict[str, Any] = {}

    @property
    def num_fragments(self) -> int:
        return int(self.fragment_facet.numel())

    def _set_kernel(self, factors: Tensor, direct: Tensor, covered: Tensor) -> None:
        idx = factors.indices()
        g = _sparse(idx[0], idx[1], factors.values(), tuple(factors.shape), self.background.dtype,
                    ordered=factors.is_coalesced())
        self.register_buffer("gather", g.to(self.background.device), persistent=False)
        self.register_buffer("direct", direct.to(self.background), persistent=False)
        self.register_buffer("open_sky", (1.0 - covered).clamp_min(0.0).to(self.background), persistent=False)

    def forward(self, reflectance: Tensor, irradiance: Tensor, spd: Tensor, camera: Camera | None = None,
                shading: str = "gather") -> Tensor:
        """:func:`gathered_image` (with a camera) or :func:`gathered_radiance` (without) of this operator."""
        if camera is None:
            return gathered_radiance(self, reflectance, irradiance, spd, shading=shading)
        return gathered_image(self, reflectance, irradiance, spd, camera, shading=shading)

    def extra_repr(self) -> str:
        return (f"height={self.height}, width={self.width}, facets={self.num_facets}, "
                f"fragments={self.num_fragments}, supersample={self.supersample}, samples={self.samples}")


def _cache_key(scene: Scene, view: View, light: Any, s: int, samples: int, seed: int) -> tuple:
    c = scene.corners.detach()
    finger = (scene.num_facets, float(c.double().sum()), float(c.double().square().sum()), str(scene.dtype),
              str(scene.device))
    return (id(scene), finger, view, _light_key(light), s, samples, seed)


def gather_operator(
    scene: Scene,
    view: View,
    light: str | Tensor | Sequence[float] = "uniform",
    *,
    supersample: int = 3,
    samples: int = 4,
    seed: int = 0,
    shading: str = "gather",
    stride: int = 1,
    cache: bool = True,
) -> Gather:
    """Cast a view's rays once and build its gather operator (cached per scene, view, light and settings).

    Args:
        scene: The scene (the facets whose irradiance is solved: user facets or refined leaves).
        view: The :class:`~torch_interreflect.camera.View`.
        light: As for :func:`~torch_interreflect.lights.light_geometry`: ``"uniform"``, ``"sky"``, a direction
            ``[3]`` (the way the light travels), a material name or boolean mask ``[F]`` (area light), or a factor
            ``[F]`` (used per hit facet).
        supersample: Sub-pixel rays per pixel side (anti-aliasing; the direct sun is shadow-tested per ray).
        samples: Visibility rays per side of a target facet for pairs a third facet could block.
        seed: Seed of the visibility jitter.
        shading: ``"gather"`` builds everything; ``"flat"`` only the coverage (no kernel, no light needed).
        stride: Evaluate the gather (and the sky's open part) at one point per ``stride × stride`` pixels and per
            facet, and interpolate bilinearly to the pixels on the same facet (about ``stride²`` times less work;
            the sun's shadow rays stay per sub-pixel ray). ``1``: at every pixel.
        cache: Reuse an operator built for the same arguments (the scene by identity and geometry).

    Returns:
        The :class:`Gather`, in the scene's dtype and device; ``info`` holds pairs, rays and seconds.

    Example:
        >>> import torch_interreflect as ti
        >>> from torch_interreflect.camera import View, gather_operator
        >>> scene = ti.scenes.v_groove(90.0, divisions=2)
        >>> view = View((0.03, 0.03, 0.1), (0.03, 0.03, 0.0), (0, 1, 0), height=8, width=8)
        >>> op = gather_operator(scene, view, [0.0, 0.0, -1.0])  # a sun straight down
        >>> op.gather.shape, op.direct.shape == (op.num_fragments,)
        (torch.Size([81, 8]), True)
    """
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a Scene; got {type(scene).__name__}")
    if not isinstance(view, View):
        raise TypeError(f"view must be a torch_interreflect.camera.View; got {type(view).__name__}")
    if shading not in ("gather", "flat"):
        raise ValueError(f"shading must be 'gather' or 'flat'; got {shading!r}")
    if isinstance(supersample, bool) or int(supersample) != supersample or int(supersample) < 1:
        raise ValueError(f"supersample must be an integer >= 1; got {supersample!r}")
    if isinstance(stride, bool) or int(stride) != stride or int(stride) < 1:
        raise ValueError(f"stride must be an integer >= 1; got {stride!r}")
    key = (*_cache_key(scene, view, light, int(supersample), int(samples), int(seed)), int(stride))
    op = _CACHE.get(key) if cache else None
    if op is None:
        t0 = time.perf_counter()
        caster = RayCaster(scene.to(torch.float64).to("cpu"))
        frag = _primary(scene, view, int(supersample), caster)
        op = Gather(view, frag, scene.num_facets, scene.dtype, scene.device, int(supersample), int(samples))
        op._frag, op._caster = frag, caster  # kept until the kernel is built
        op.info["seconds"] = {"primary": time.perf_counter() - t0}
    if shading == "gather" and op.gather is None:
        frag = op._frag
        if int(stride) == 1:
            factors, covered, info = point_form_factors(scene, frag["centre"], frag["facet"], samples=samples,
                                                        seed=seed, caster=op._caster)
        else:
            centres, facets, weights = _coarse(frag, view.height, view.width, scene.num_facets, int(stride))
            factors, covered, info = point_form_factors(scene, centres, facets, samples=samples, seed=seed,
                                                        caster=op._caster)
            factors = torch.sparse.mm(weights, factors).coalesce()
            covered = torch.sparse.mm(weights, covered[:, None])[:, 0]
            info["points"] = int(centres.shape[0])
        t0 = time.perf_counter()
        op._set_kernel(factors, _direct(scene, light, frag, op._caster, covered, factors), covered)
        op.info.update(pairs=info["pairs"], rays=info["rays"], points=info.get("points", op.num_fragments))
        op.info["seconds"].update(kernel=info["seconds"], direct=time.perf_counter() - t0)
        del op._frag, op._caster
    if cache:
        _CACHE[key] = op
        _CACHE.move_to_end(key)
        while len(_CACHE) > CACHE_SIZE:
            _CACHE.popitem(last=False)
    return op


# ------------------------------------------------------------------------------------------- images
def _columns(m: Tensor, x: Tensor) -> Tensor:
    """``m [R, N] @ x [..., N, C]`` → ``[..., R, C]`` as one (sparse) matrix product over all columns."""
    lead, n, c = x.shape[:-2], x.shape[-2], x.shape[-1]
    cols = x.movedim(-2, 0).reshape(n, -1)
    out = m.to(device=x.device, dtype=x.dtype) @ cols
    return out.reshape(m.shape[0], *lead, c).movedim(0, -2)


def _to_image(op: Gather, pixels: Tensor) -> Tensor:
    """``[..., H·W, C]`` → ``[..., C, H, W]``."""
    return pixels.movedim(-1, -2).reshape(*pixels.shape[:-2], pixels.shape[-1], op.height, op.width)


def _check_spectra(op: Gather, reflectance: Tensor, irradiance: Tensor) -> tuple[Tensor, Tensor]:
    r = reflectance if reflectance.ndim >= 2 else reflectance[:, None]
    if r.shape[-2] != op.num_facets or irradiance.ndim < 2 or irradiance.shape[-2] != op.num_facets:
        raise ShapeError(
            f"reflectance and irradiance must be [..., F, L] with F = {op.num_facets} (the operator's scene); got "
            f"{list(reflectance.shape)} and {list(irradiance.shape)}"
        )
    r, E = torch.broadcast_tensors(r, irradiance)
    return r, E


def gathered_radiance(op: Gather, reflectance: Tensor, irradiance: Tensor, spd: Tensor | None = None, *,
                      shading: str = "gather", direct: Tensor | None = None) -> Tensor:
    """Spectral radiance images ``r(x) E(x) / π`` of a view, per pixel (W·sr⁻¹·m⁻²·nm⁻¹).

    ``E(x) = g0(x) S + Σ_j G[x, j] B_j`` with ``B = R E`` the facets' radiosity (``shading="gather"``), or the
    hit facet's own ``E`` (``"flat"``). Linear in ``B`` and ``S``; differentiable in ``reflectance``,
    ``irradiance`` and ``spd``.

    Args:
        op: The view's :class:`Gather` (:func:`gather_operator`).
        reflectance: In [0, 1]. Shape ``[..., F, L]`` (or ``[F]`` grey).
        irradiance: The solved facet irradiance ``E`` (e.g. :func:`torch_interreflect.solve` with
            ``E0 = g ⊗ S``). Shape ``[..., F, L]``.
        spd: The light's spectrum ``S`` as given to the solve (irradiance of a sun, radiance of a sky or area
            light, the uniform irradiance). Shape ``[..., L]``. Needed for ``"gather"``.
        shading: ``"gather"`` or ``"flat"``.
        direct: ``g0`` per fragment in place of ``op.direct``, e.g. a mix of lights
            ``a · op.open_sky · π + (1 − a) · op.direct``. Shape ``[K]``.

    Returns:
        Radiance images. Shape ``[..., L, H, W]``.
    """
    if shading not in ("gather", "flat"):
        raise ValueError(f"shading must be 'gather' or 'flat'; got {shading!r}")
    r, E = _check_spectra(op, reflectance, irradiance)
    if shading == "flat":
        return _to_image(op, _columns(op.coverage, r * E / math.pi))
    if op.gather is None:
        raise ValueError("this operator was built with shading='flat'; build it with gather_operator(..., "
                         "shading='gather') to gather")
    if spd is None:
        raise ValueError("shading='gather' needs the light's spectrum spd [..., L] (the S of E0 = g ⊗ S)")
    S = torch.as_tensor(spd, dtype=E.dtype, device=E.device)
    if S.shape[-1] != E.shape[-1]:
        raise ShapeError(f"spd must be [..., L] with L = {E.shape[-1]}; got {list(S.shape)}")
    if direct is None:
        direct = op.direct
    elif direct.shape != (op.num_fragments,):
        raise ShapeError(f"direct must be [K] with K = {op.num_fragments} (one per fragment); got {list(direct.shape)}")
    direct = direct.to(device=E.device, dtype=E.dtype)
    e_frag = direct[:, None] * S[..., None, :] + _columns(op.gather, r * E)  # [..., K, L]
    r_frag = r.index_select(-2, op.fragment_facet.to(E.device))
    r_frag, e_frag = torch.broadcast_tensors(r_frag, e_frag)
    return _to_image(op, _columns(op.pixel_fragments, r_frag * e_frag / math.pi))


def gathered_image(op: Gather, reflectance: Tensor, irradiance: Tensor, spd: Tensor | None, camera: Camera, *,
                   shading: str = "gather", direct: Tensor | None = None) -> Tensor:
    """Linear camera RGB images of a view: :func:`gathered_radiance` through the camera's sensitivities.

    Arguments as for :func:`gathered_radiance` (``direct`` included), and ``camera`` (a
    :class:`~torch_interreflect.camera.Camera` whose grid has the ``L`` wavelengths). ``shading="gather"``
    (per-pixel final gather) or ``"flat"`` (one colour per facet).

    Returns:
        Camera RGB. Shape ``[..., C, H, W]`` (``[3, H, W]`` for unbatched inputs).

    Example:
        >>> import torch, torch_interreflect as ti
        >>> from torch_interreflect.camera import View, gather_operator, gathered_image
        >>> scene = ti.scenes.v_groove(90.0, divisions=2)
        >>> wl = ti.spectral.wavelengths(); cam = ti.Camera.from_colour("Nikon 5100 (NPL)", wl)
        >>> op = gather_operator(scene, View((0.03, 0.03, 0.1), (0.03, 0.03, 0.0), (0, 1, 0), height=8, width=8))
        >>> r = torch.full((8, 31), 0.5); S = torch.ones(31)
        >>> E = ti.solve(ti.form_factors(scene), r, S.expand(8, 31))
        >>> gathered_image(op, r, E, S, cam).shape
        torch.Size([3, 8, 8])
    """
    rad = gathered_radiance(op, reflectance, irradiance, spd, shading=shading, direct=direct)  # [..., L, H, W]
    rgb = camera(rad.movedim(-3, -1))  # [..., H, W, C]
    return rgb.movedim(-1, -3)


def render_view(scene: Scene, reflectance: Tensor, irradiance: Tensor, spd: Tensor | None, camera: Camera | None,
                view: View, light: str | Tensor | Sequence[float] = "uniform", *, shading: str = "gather",
                supersample: int = 3, samples: int = 4) -> Tensor:
    """One call from solved facets to an image: the cached :func:`gather_operator`, then the image.

    ``reflectance``, ``irradiance`` (solved for ``E0 = g ⊗ spd``, ``g`` the light's geometric factor), ``spd`` and
    ``shading`` as for :func:`gathered_radiance`; ``view``, ``light``, ``supersample`` and ``samples`` as for
    :func:`gather_operator`. With a :class:`~torch_interreflect.camera.Camera` the result is camera RGB
    ``[..., C, H, W]`` (:func:`gathered_image`), with ``camera=None`` spectral radiance ``[..., L, H, W]``.
    """
    op = gather_operator(scene, view, light, supersample=supersample, samples=samples, shading=shading)
    if camera is None:
        return gathered_radiance(op, reflectance, irradiance, spd, shading=shading)
    return gathered_image(op, reflectance, irradiance, spd, camera, shading=shading)
