"""Form factors between facets: Lambert's contour formula integrated by adaptive Gauss quadrature.

``F_ij`` (DESIGN.md §1-2) is computed once per unordered pair that can exchange light:

1. **Culling** (exact, free): ``i`` and ``j`` exchange light only if each has a part strictly in front of
   the other's plane; coplanar facets never do.
2. **Quadrature**: the exact point-to-polygon factor (Lambert's contour formula, with the target clipped at
   the horizon of the integration facet where it crosses it) is integrated over the smaller facet of the
   pair with a Gauss-Legendre rule whose order follows the pair's distance / size ratio. Pairs that share an
   edge or a vertex get a rule graded toward the shared edge/vertex, where the integrand has its
   logarithmic singularity (a pair along one line from a shared corner over the facet of the shorter edge,
   :func:`~.pairs.corner_edge_contacts`). Reciprocity gives the other direction.
3. **Occlusion**: pairs that some third facet could block (its plane separates the two facets and its box
   overlaps theirs) get a fractional, kernel-weighted visibility from rays cast with Embree.

``method="monte_carlo"`` is the paper's estimator (its §5.2), kept for comparison.
"""

from __future__ import annotations

import contextlib
import time
from typing import Any, Literal

import numpy as np
import torch
from torch import Tensor
from tqdm.auto import tqdm

from .._checks import check_count
from .._deprecation import renamed_keywords
from .._sparse import sparse_matrix
from .._threads import compiled_work
from ..errors import ValueRangeError
from ..geometry._polygon import (
    clip_polygons,
    plane_eps,
    rotate_to_plane_edge,
)
from ..geometry.scene import Scene
from .checks import check_row_sums, check_sums, warn_if_wrong_side
from .compiled import launch, loops
from .fused import Backend, fan_sums, group_sums, grouped_sums, resolve_backend
from .montecarlo import monte_carlo
from .operator import FormFactors
from .pairs import (
    SPARSE_DENSITY,
    PairClasses,
    classify_pairs,
    corner_edge_contacts,
    facing_pairs,
    order_pairs,
    rule_groups,
)
from .rules import quadrature_rule
from .visibility import VISIBILITY_ANGLE, PointVisibility, blocker_candidates, check_visibility_options
from .visibility_grad import VISIBILITY_GRAD_POINTS, visibility_gradient

__all__ = ["PairClasses", "classify_pairs", "form_factors", "integrate_clipped", "integrate_groups", "pair_values",
           "rule_groups"]

#: Dense storage up to this many facets; sparse CSR above it when at most ``SPARSE_DENSITY`` is nonzero.
_DENSE_MAX_FACETS = 4096


# ------------------------------------------------------------------------------------ main entry
@renamed_keywords(tol="quadrature_tol", samples="rays_per_facet")
def form_factors(
    scene: Scene,
    *,
    method: Literal["quadrature", "monte_carlo"] = "quadrature",
    occlusion: Literal["auto"] | bool = "auto",
    quadrature_tol: float = 1e-6,
    adjacent_order: int | None = None,
    visibility_samples: int = 3,
    visibility_tol: float | None = None,
    visibility_angle: float | None = VISIBILITY_ANGLE,
    visibility_jitter: bool = True,
    visibility_grad_points: int = VISIBILITY_GRAD_POINTS,
    rays_per_facet: int = 100_000,
    layout: Literal["auto", "dense", "sparse"] = "auto",
    generator: torch.Generator | None = None,
    chunk_points: int = 1 << 18,
    progress: bool | None = None,
    backend: Backend = "auto",
) -> FormFactors:
    """Form factors ``F_ij`` of a scene: the fraction of light leaving facet i that arrives at facet j.

    The dense kernel holds ``[F, F]`` matrices (the facing test, and the result when dense) and ~200 bytes per
    facet pair that can exchange light; the memory is estimated before anything large is allocated, and a
    scene that does not fit raises :class:`~torch_interreflect.errors.InsufficientMemoryError` (use
    :func:`~torch_interreflect.hierarchical_form_factors` for such scenes).

    Args:
        scene: The scene.
        method: ``"quadrature"`` (exact contour formula with adaptive Gauss quadrature, the default) or
            ``"monte_carlo"`` (the paper's estimator: ``rays_per_facet`` cosine-distributed rays per facet).
        occlusion: ``"auto"`` casts visibility rays only for pairs that some third facet could block (none in
            a V-groove, a box corner or a closed box); ``True`` casts them for every pair, ``False`` ignores
            occlusion.
        quadrature_tol: Target relative accuracy of each entry; sets the quadrature order of every pair
            (formerly ``tol``).
        adjacent_order: Gauss order (per direction) for pairs that share an edge or a vertex (default from
            ``quadrature_tol``; these use rules graded toward the shared edge).
        visibility_samples: Points per direction on the target facet for visibility rays: every quadrature
            point of a pair that a third facet could block casts ``visibility_samples²`` kernel-weighted rays.
        visibility_tol: Cells of that grid on a shadow boundary (their ray disagrees with a neighbour's) are split
            2 × 2, again and again, while they carry more than this share of the point's kernel weight, so the
            visible fraction converges (e.g. ``1e-3``); ``None`` (default) keeps the fixed grid, which is faster
            but leaves an error of the grid's order. See
            :class:`~torch_interreflect.formfactors.visibility.PointVisibility`.
        visibility_angle: With the fixed grid: a target that looks small from the pair's other facet (angular
            size ``α``: diameter over the centroids' distance) gets ``ceil(α / visibility_angle)`` points per
            direction, at most ``visibility_samples``; ``None`` gives every target ``visibility_samples``. On the
            Cornell box at 3,200 facets the default casts 5.8× fewer rays (kernel 2.6× faster) for 0.206 % against
            0.187 % error (``benchmarks/results/visibility.md``).
        visibility_jitter: With the fixed grid, each quadrature point casts its rays to one point per cell at an
            offset of its own (a deterministic low-discrepancy lattice,
            :func:`~torch_interreflect.formfactors.visibility.grid_offsets`) rather than to the cell midpoints, so
            the points of a pair sample the target at many more places and a thin blocker cannot hide (or miss)
            a whole target; ``False`` casts to the midpoints (the behaviour of 0.1).
        visibility_grad_points: When the corners require grad: points per occluded pair (on the pair's domain)
            for the part of the gradient that ray-cast visibility leaves out (shadow edges moving, and the
            interior term's spread over the visible part; :mod:`~torch_interreflect.formfactors.visibility_grad`).
            ``0`` leaves it out (the interior term ``∂f · vis`` only, as in 0.1).
        rays_per_facet: Rays per facet for ``method="monte_carlo"`` (formerly ``samples``).
        layout: Storage of the matrix: dense, sparse CSR, or chosen by size and density.
        generator: Random generator for ``method="monte_carlo"``.
        chunk_points: Quadrature points × polygon corners evaluated at once; the default keeps every
            temporary (a few MB) in cache, which is several times faster than larger blocks.
        progress: Show a progress bar (default: only for large scenes).
        backend: ``"fused"`` / ``"auto"`` (default) evaluate the quadrature in one compiled multi-core loop per
            chunk of pairs; when the scene's vertices require grad (on the CPU), with its compiled adjoint.
            ``"torch"`` uses torch tensors throughout (the reference; autograd keeps every quadrature point's
            temporaries). See :mod:`~torch_interreflect.formfactors.fused`.

    Returns:
        :class:`~torch_interreflect.FormFactors` in the scene's dtype and device, with ``info``
        saying what was done (pairs, quadrature points, rays, seconds, ``max_row_sum``).

    Raises:
        InsufficientMemoryError: the estimated memory exceeds what the machine has available.
        GeometryError: a row sums above 1 by more than the quadrature's tolerance (overlapping or intersecting
            facets that ``Scene(duplicates="keep")`` let through).

    Warns:
        GeometryWarning: no facet pair can exchange light although the facets' other sides could (normals
            pointing out of a concave mesh: see ``Scene.from_trimesh(side=...)``).

    Gradients:
        With ``method="quadrature"`` the matrix keeps the graph of ``scene.corners`` (a scene built from vertices
        that require grad, or from a parameterised builder such as ``ti.scenes.v_groove(angle)`` with a tensor
        angle): ``F`` is the quadrature of Lambert's contour formula, a smooth function of the corners, so
        autograd gives its exact derivative while the pair classes, the Gauss orders and the clipping stay fixed
        (they are chosen from the geometry but are piecewise constant in it). Measured against central finite
        differences in float64: ``d mean(E) / d angle`` of a V-groove to 8e-11 relative, Howell's C-14 derivative
        to 6e-8 (``tests/formfactors/test_geometry_grad.py``). The compiled adjoint (default) and torch autograd
        (``backend="torch"``) agree to rounding (2e-15 relative); the adjoint keeps O(pairs) memory and gives first
        derivatives only. Occluded pairs: ray-cast visibility is constant for autograd, and the shadow terms are
        added by edge sampling (``visibility_grad_points``, :mod:`~torch_interreflect.formfactors.visibility_grad`):
        on a W fold whose ridge occludes, the heights' derivatives are 0.2–3.5 % from fitted differences (53–76 %
        without them); on one large plate behind a moving blocker, 1.9 % / 0.3 % from the exact derivatives at
        ``visibility_grad_points=1024`` (36 % / 1 % at the default 32: large facets need more points), where they
        were 0 (blocker moving sideways) and 10 % off (plate moving) without them. Not included:
        ``method="monte_carlo"`` (no gradient). ``areas`` of the result are detached.

    Shape:
        - output ``.to_dense()``: ``[F, F]``

    Example:
        >>> import torch_interreflect as ti
        >>> K = ti.form_factors(ti.scenes.closed_box(divisions=2))
        >>> float(K.row_sums().min()) > 0.999999
        True
    """
    _check_arguments(scene, method, occlusion, quadrature_tol, layout, backend)
    check_visibility_options(visibility_samples, visibility_tol, visibility_angle, visibility_jitter)
    check_count(visibility_grad_points, "visibility_grad_points", minimum=0)
    t0 = time.perf_counter()
    F = scene.num_facets
    if progress is None:
        progress = F >= 2000
    if layout == "auto" and F <= _DENSE_MAX_FACETS:
        layout = "dense"
    if method == "monte_carlo":
        rows, cols, vals, info = monte_carlo(scene, rays_per_facet, generator)
    else:
        itemsize = torch.empty(0, dtype=scene.dtype).element_size()
        # the compiled path: torch's glue on one thread, the compiled loops and rays on the caller's threads (the
        # torch path, and inputs that require grad, keep torch's threads)
        work = compiled_work() if resolve_backend(backend, scene.corners) else contextlib.nullcontext()
        with work:
            dom, tgt, value, areas, info = _quadrature(
                scene, occlusion, quadrature_tol, adjacent_order, visibility_samples, chunk_points, progress,
                output=(layout, itemsize), backend=backend, visibility_tol=visibility_tol,
                visibility_angle=visibility_angle, visibility_jitter=visibility_jitter,
                visibility_grad_points=visibility_grad_points,
            )
    out_dtype, dev = scene.dtype, scene.device
    direct = None
    if method == "quadrature":  # dense output: written straight from the pairs where it can be
        direct = _dense_direct(dom, tgt, value, areas, layout, out_dtype, (quadrature_tol, occlusion, info))
        if direct is None:
            rows, cols, vals = pair_entries(areas, dom, tgt, value)
    if direct is not None:
        (matrix, nnz), layout = direct, "dense"
    else:
        info["max_row_sum"] = check_row_sums(rows, vals, F, quadrature_tol, method, occlusion,
                                             info.get("occluded_facets"))
        matrix, layout = assemble(rows, cols, vals, F, layout, out_dtype)
        nnz = int(rows.numel())
    info.update(method=method, seconds=time.perf_counter() - t0, layout=layout, nnz=nnz)
    if method == "quadrature":
        info["quadrature_tol"] = quadrature_tol  # the solver's closure-error bound reads it
    return FormFactors(matrix.to(dev), scene.areas.detach().to(out_dtype), info)


def _check_arguments(
    scene: Scene, method: str, occlusion: Any, quadrature_tol: float, layout: str, backend: str = "auto"
) -> None:
    if not isinstance(scene, Scene):
        raise TypeError(f"form_factors expects a Scene; got {type(scene).__name__}")
    if method not in ("quadrature", "monte_carlo"):
        raise ValueError(f"method must be 'quadrature' or 'monte_carlo'; got {method!r}")
    if occlusion not in ("auto", True, False):
        raise ValueError(f"occlusion must be 'auto', True or False; got {occlusion!r}")
    if not (0.0 < quadrature_tol < 1.0):
        raise ValueRangeError(f"quadrature_tol must lie in (0, 1); got {quadrature_tol}")
    if layout not in ("auto", "dense", "sparse"):
        raise ValueError(f"layout must be 'auto', 'dense' or 'sparse'; got {layout!r}")
    if backend not in ("auto", "fused", "torch"):
        raise ValueError(f"backend must be 'auto', 'fused' or 'torch'; got {backend!r}")


def _dense_direct(dom: Tensor, tgt: Tensor, value: Tensor, areas: Tensor, layout: str, dtype: torch.dtype,
                  check: tuple[float, Any, dict]) -> tuple[Tensor, int] | None:
    """The dense ``[F, F]`` matrix written straight from the pairs by a compiled loop (no ``[2P]`` entry lists),
    with its row sums checked as :func:`~.checks.check_row_sums` does (``check = (quadrature_tol, occlusion,
    info)``; sets ``info["max_row_sum"]``); None where the entries are needed (sparse output, autograd, no numba).
    """
    kern = loops("pairs")
    F = areas.numel()
    if kern is None or value.requires_grad or dtype not in (torch.float32, torch.float64) or layout == "sparse":
        return None
    # numpy here, not torch: a torch parallel region right before the launch leaves OpenMP workers spinning
    if layout == "auto" and _sparse_wins(F, 2 * np.count_nonzero(value.numpy() > 0)):
        return None
    mat = torch.from_numpy(np.zeros((F, F), dtype=np.float32 if dtype == torch.float32 else np.float64))
    blocks = max(1, min(4 * torch.get_num_threads(), (dom.numel() >> 14) + 1))
    sums = np.zeros((blocks, F))
    nnz = int(launch(kern.dense_entries, *(t.contiguous().numpy() for t in (areas, dom, tgt, value)), mat.numpy(),
                     sums))
    quadrature_tol, occlusion, info = check
    info["max_row_sum"] = check_sums(torch.from_numpy(sums.sum(0)), quadrature_tol, "quadrature", occlusion,
                                     info.get("occluded_facets"))
    return mat, nnz


def _quadrature(
    scene: Scene,
    occlusion: Literal["auto"] | bool,
    tol: float,
    adjacent_order: int | None,
    visibility_samples: int,
    chunk_points: int,
    progress: bool,
    output: tuple[str, int] = ("dense", 8),
    backend: Backend = "auto",
    visibility_tol: float | None = None,
    visibility_angle: float | None = VISIBILITY_ANGLE,
    visibility_jitter: bool = True,
    visibility_grad_points: int = 0,
) -> tuple[Tensor, Tensor, Tensor, Tensor, dict]:
    """``(dom, tgt, value, areas, info)``: the pairs, ``value = A_dom F_dom,tgt`` (m², clamped at 0), the facets'
    float64 areas, and what was done (see :func:`form_factors`)."""
    sc = scene.to(torch.float64).to("cpu")
    F = sc.num_facets
    eps = plane_eps(scene)
    info: dict = {}

    t = time.perf_counter()
    iu, ju = facing_pairs(sc, eps, output)
    info["pairs"] = int(iu.numel())
    info["seconds_cull"] = time.perf_counter() - t
    if iu.numel() == 0:
        warn_if_wrong_side(sc, eps)
        empty = torch.zeros(0, dtype=torch.int64)
        info.update(points=0, rays=0, occluded_pairs=0, occluded_facets=torch.zeros(F, dtype=torch.bool))
        return empty, empty, torch.zeros(0, dtype=torch.float64), sc.areas, info

    dom, tgt, value, need, vis = pair_values(
        sc, iu, ju, occlusion, tol, adjacent_order, visibility_samples, chunk_points, progress, info, eps,
        backend=backend, visibility_tol=visibility_tol, visibility_angle=visibility_angle,
        visibility_jitter=visibility_jitter, visibility_grad_points=visibility_grad_points,
    )

    # facets with a pair whose visibility was estimated by rays: their row sums are estimates, not exact
    approx = torch.zeros(F, dtype=torch.bool)
    approx[dom[need]] = True
    approx[tgt[need]] = True
    info.update(occluded_pairs=int(torch.count_nonzero(need)), rays=vis.rays if vis else 0, occluded_facets=approx)

    return dom, tgt, value, sc.areas, info


def pair_entries(areas: Tensor, dom: Tensor, tgt: Tensor, value: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Matrix entries ``(rows, cols, F_ij)`` of both directions of pairs with ``value = A_dom F_dom,tgt``
    (reciprocity: ``F_tgt,dom = value / A_tgt``); zero entries dropped.

    Shape:
        - areas: ``[F]`` (m²); dom, tgt, value: ``[P]``
        - output: three ``[≤ 2P]`` tensors
    """
    kern = loops("pairs")
    if kern is not None and value.device.type == "cpu" and not value.requires_grad:
        out = launch(kern.pair_entries, *(t.contiguous().numpy() for t in (areas.to(value.dtype), dom, tgt, value)))
        return tuple(torch.from_numpy(a) for a in out)  # type: ignore[return-value]
    keep = torch.nonzero(value > 0).reshape(-1)  # areas are positive: both directions are kept or dropped together
    dom, tgt, value = dom[keep], tgt[keep], value[keep]
    return torch.cat([dom, tgt]), torch.cat([tgt, dom]), torch.cat([value / areas[dom], value / areas[tgt]])


def _sparse_wins(F: int, nnz: int) -> bool:
    """``layout="auto"``: sparse CSR above ``_DENSE_MAX_FACETS`` facets when at most ``SPARSE_DENSITY`` is nonzero."""
    return F > _DENSE_MAX_FACETS and nnz <= SPARSE_DENSITY * F * F


def assemble(rows: Tensor, cols: Tensor, vals: Tensor, F: int, layout: str, dtype: torch.dtype) -> tuple[Tensor, str]:
    """The ``[F, F]`` matrix of the entries in ``dtype``, dense or CSR, and the layout used.

    ``layout="auto"`` is dense up to ``_DENSE_MAX_FACETS`` facets and whenever more than ``SPARSE_DENSITY`` of
    the entries are nonzero, sparse CSR otherwise. Entries are float64 on the CPU (as the quadrature gives them).
    """
    if layout == "auto":
        layout = "sparse" if _sparse_wins(F, rows.numel()) else "dense"
    if layout == "dense":
        mat = torch.zeros(F, F, dtype=dtype, device=vals.device)  # in the output dtype: no [F, F] copy
        kern = loops("pairs")
        if kern is not None and vals.device.type == "cpu" and not vals.requires_grad and dtype in (torch.float32,
                                                                                                  torch.float64):
            launch(kern.scatter_dense, rows.contiguous().numpy(), cols.contiguous().numpy(),
                   vals.contiguous().numpy(), mat.numpy())
        else:
            mat[rows, cols] = vals.to(dtype)
        return mat, layout
    return sparse_matrix(rows, cols, vals, (F, F), dtype), layout


def pair_values(
    sc: Scene,
    iu: Tensor,
    ju: Tensor,
    occlusion: Literal["auto"] | bool,
    tol: float,
    adjacent_order: int | None,
    visibility_samples: int,
    chunk_points: int,
    progress: bool,
    info: dict,
    eps: float,
    vis: PointVisibility | None = None,
    backend: Backend = "auto",
    visibility_tol: float | None = None,
    visibility_angle: float | None = VISIBILITY_ANGLE,
    visibility_jitter: bool = True,
    visibility_grad_points: int = 0,
) -> tuple[Tensor, Tensor, Tensor, Tensor, PointVisibility | None]:
    """``A_i F_ij`` for given pairs ``(iu, ju)`` of mutually facing facets of ``sc`` (float64, CPU).

    Returns ``(dom, tgt, value, need, vis)``: each pair reordered so that ``dom`` is the smaller facet (the
    integration domain; or the one whose edge lies on the other's, :func:`~.pairs.corner_edge_contacts`),
    ``value = A_dom F_dom,tgt`` (clamped at 0), ``need`` the pairs whose visibility came from rays, and the
    visibility object (``vis`` when given, reused across calls). Adds ``points``, ``seconds_quadrature``,
    ``seconds_visibility``, ``pairs_adjacent`` and ``pairs_clipped`` to ``info``
    (accumulating over calls). ``tol`` is the quadrature tolerance (``quadrature_tol`` of :func:`form_factors`);
    ``backend``, ``visibility_tol``, ``visibility_angle``, ``visibility_jitter``, ``visibility_grad_points``: see
    :func:`form_factors` (a ``vis`` given keeps its own; ``visibility_grad_points`` defaults to 0 here).
    """
    areas = sc.areas
    # integrate over the smaller facet of each pair (the "domain"), contour over the other ("target"); pairs along
    # one line from a shared corner are turned around below (corner_edge_contacts)
    dom, tgt = order_pairs(areas, iu, ju)

    t = time.perf_counter()
    value = torch.empty(dom.numel(), dtype=torch.float64)  # A_dom F_dom,tgt
    cls = classify_pairs(sc, dom, tgt, tol, adjacent_order, eps)
    dom, tgt, cls = corner_edge_contacts(sc, dom, tgt, cls)
    groups, clipped = rule_groups(cls)

    # occlusion: pairs that a third facet could block get a visible fraction at every quadrature point
    t_vis = time.perf_counter()
    if occlusion is False:
        need = torch.zeros(dom.numel(), dtype=torch.bool)
    elif occlusion is True:
        need = torch.ones(dom.numel(), dtype=torch.bool)
    else:
        need = blocker_candidates(sc, dom, tgt, eps)
    if vis is None and bool(need.any()):
        vis = PointVisibility(sc, visibility_samples, tol=visibility_tol, angle=visibility_angle,
                              jitter=visibility_jitter)
    vis_before = vis.seconds if vis is not None else 0.0
    seconds_vis = time.perf_counter() - t_vis

    bar = tqdm(total=int(dom.numel()), desc="form factors", unit="pair", leave=False,
               disable=None if progress else True, mininterval=1.0)
    visibility = (need, vis, backend)
    points = integrate_groups(sc, dom, tgt, cls, groups, visibility, value, chunk_points, eps, bar)
    points += integrate_clipped(sc, dom, tgt, cls, clipped, visibility, value, chunk_points, eps, bar)
    bar.close()
    value = value.clamp_min(0.0) if value.requires_grad else value.clamp_min_(0.0)
    if value.requires_grad and vis is not None and visibility_grad_points > 0 and bool(need.any()):
        # what autograd misses with ray-cast visibility: zero in value, the shadow terms in the gradient
        t_grad = time.perf_counter()
        occluded = torch.nonzero(need).reshape(-1)
        value = value.index_add(0, occluded, visibility_gradient(sc, dom[occluded], tgt[occluded], vis.caster, eps,
                                                                 points=visibility_grad_points))
        info["seconds_visibility_grad"] = info.get("seconds_visibility_grad", 0.0) + time.perf_counter() - t_grad
    seconds_vis += (vis.seconds if vis is not None else 0.0) - vis_before
    for key, add in (
        ("points", int(points)),
        ("seconds_quadrature", time.perf_counter() - t - seconds_vis),
        ("seconds_visibility", seconds_vis),
        ("pairs_adjacent", int(torch.count_nonzero(cls.has_edge)) + int(torch.count_nonzero(cls.has_vertex))),
        ("pairs_clipped", int(torch.count_nonzero(cls.clip_t | cls.clip_d))),
    ):
        info[key] = info.get(key, 0) + add
    return dom, tgt, value, need, vis


def integrate_groups(sc: Scene, dom: Tensor, tgt: Tensor, cls: PairClasses, groups: list[tuple[str, Tensor, int]],
                     visibility: tuple[Tensor, Any, Backend], value: Tensor, chunk_points: int, eps: float,
                     bar: Any) -> int:
    """Integrate the pairs of each rule group (domain unclipped) into ``value``; returns the quadrature points.

    ``visibility = (need, vis, backend)``: the pairs that get ray-cast visible fractions, the
    :class:`~.visibility.PointVisibility`, and the backend of :func:`~.fused.group_sums` (the compiled loop, or
    the same maths in torch for autograd and other devices).
    """
    need, vis, backend = visibility
    corners, normals, cent = sc.corners, sc.normals, sc.centroids
    rays = vis is not None and bool(need.any())
    points = 0
    visible = []  # (rule, pairs) whose points are all visible: one launch for all groups
    for kind, sel, n in groups:
        rule = quadrature_rule(kind, n, torch.float64, torch.device("cpu"))
        free = sel
        if rays:
            occluded = need[sel]
            if bool(occluded.any()):
                group_sums(corners, normals, cent, dom, tgt, cls.shift, cls.clip_t, rule, eps, need, vis, backend,
                           chunk_points=chunk_points, select=sel[occluded], out=value)
                free = sel[~occluded]
                bar.update(sel.numel() - free.numel())
        visible.append((rule, free))
        points += sel.numel() * rule[0].numel()
    grouped_sums(corners, normals, cent, (dom, tgt, cls.shift, cls.clip_t), visible, eps, value, backend, chunk_points)
    bar.update(sum(sel.numel() for _, sel in visible))
    return points


def integrate_clipped(sc: Scene, dom: Tensor, tgt: Tensor, cls: PairClasses, clipped: Tensor,
                      visibility: tuple[Tensor, Any, Backend], value: Tensor, chunk_points: int, eps: float,
                      bar: Any) -> int:
    """Integrate the pairs whose domain crosses the target's plane into ``value``; returns the quadrature points.

    The clipped polygon (at most five corners) is rotated so that its edge on the target's plane, where the
    integrand is singular when the two touch, comes first; the fan triangle on that edge gets the edge-graded
    rule, the others (which touch it at one corner) the vertex-graded rule (:func:`~.fused.fan_sums`).
    ``visibility`` as in :func:`integrate_groups`.
    """
    need, vis, backend = visibility
    corners, normals, cent = sc.corners, sc.normals, sc.centroids
    points = 0
    if not clipped.numel():
        return points
    near = cls.rho[clipped] < 1.0
    n_clip = torch.where(near, torch.full_like(cls.order[clipped], cls.n_adj), cls.order[clipped].clamp_min(4))
    for n in torch.unique(n_clip).tolist():
        rules = [quadrature_rule(kind, int(n), torch.float64, torch.device("cpu")) for kind in ("edge", "vertex")]
        sub = clipped[n_clip == n]
        per = max(1, chunk_points // (rules[0][0].numel() * 5))
        for s in range(0, sub.numel(), per):
            p = sub[s : s + per]
            poly = clip_polygons(corners[dom[p]], cent[tgt[p]], normals[tgt[p]], eps)[:, :5]
            poly = rotate_to_plane_edge(poly, cent[tgt[p]], normals[tgt[p]], eps)
            target = clip_polygons(corners[tgt[p]], cent[dom[p]], normals[dom[p]], eps)[:, :5]
            value[p] = fan_sums(poly, target, normals[dom[p]], rules, dom[p], tgt[p], need[p], vis, backend)
            points += p.numel() * (rules[0][0].numel() + 2 * rules[1][0].numel())
            bar.update(p.numel())
    return points
