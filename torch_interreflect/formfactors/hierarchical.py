"""Hierarchical (clustered) form factors for large scenes: exact near field, separable far field.

The dense kernel (:func:`~torch_interreflect.form_factors`) costs ``O(F²)`` memory and time; at 20,000 facets its
pair lists alone exceed 20 GB. :func:`hierarchical_form_factors` instead builds a binary tree over the facets
(split by normal direction until a cluster's normals are coherent, then spatially at the median) and splits
the interaction of the root with itself recursively, as in hierarchical radiosity:

- **Zero blocks** (exact): every point of one cluster lies on or behind every facet plane of the other; such
  facets never exchange light (coplanar walls, back-to-back faces).
- **Far blocks** (approximated): clusters A and B whose radii are small against their distance,
  ``r_A + r_B ≤ eta·d``, and each lying entirely on or in front of every facet plane of the other (so the
  exact kernel needs no clipping between them). With ``ω = (c_B − c_A)/d``:

      F_ij ≈ (n_i·ω) (−n_j·ω) A_j V_AB / (π d²),     i ∈ A, j ∈ B   (and the same with i, j swapped)

  which is separable: its product with ``x`` needs only the cluster moments ``M_B = Σ_j n_j A_j x_j`` (one
  upward pass over the tree) and one downward pass, ``O(F + blocks)`` per product. ``A_i F_ij = A_j F_ji``
  holds exactly, so the symmetric form used by conjugate gradients stays symmetric. ``V_AB`` is a
  kernel-weighted visible fraction from ``visibility_samples²`` Embree rays between sample facets of the two
  clusters, cast only where a third facet could block (the plane-group test of the dense kernel, on cluster
  bounds); a partly visible block is split further until both sides are leaves.
- **Near field** (exact): leaf pairs that are neither zero nor far: every facet pair is evaluated by the dense
  kernel's quadrature (Lambert's contour formula, graded rules at shared edges, per-point visibility) and stored
  as a sparse CSR matrix.

Memory is ``O(F·leaf_size·(near leaves))`` for the near field plus ``O(blocks)`` for the far field, nothing
``[F, F]``. After construction every product is plain torch (CPU or CUDA, float32 or float64).

Lights: :func:`~torch_interreflect.lights.light_geometry` (``"sky"`` from the row sums, area lights from one
product) and :func:`~torch_interreflect.lights.sky` accept the operator as they accept a
:class:`~torch_interreflect.FormFactors`; ``lights.sky``'s default back-face test casts rays from every facet
that sees another's back and from every facet with ray-cast visibility, so above ~20,000 facets pass
``backfaces=False`` or use ``light_geometry(scene, K, "sky")``.
"""

from __future__ import annotations

import math
import time
from typing import Any, Literal

import numpy as np
import torch
from torch import Tensor
from tqdm.auto import tqdm

from .._checks import check_count
from .._sparse import sparse_matrix
from ..errors import ValueRangeError
from ..geometry._polygon import plane_eps
from ..geometry.raycast import RayCaster
from ..geometry.scene import Scene
from .cluster_tree import ClusterTree, build_tree, leaf_pairs, traverse
from .cluster_visibility import ClusterVisibility
from .hierarchical_operator import HierarchicalFormFactors
from .quadrature import pair_values
from .visibility import VISIBILITY_ANGLE, PointVisibility

__all__ = ["HierarchicalFormFactors", "hierarchical_form_factors"]


# ---------------------------------------------------------------------------------------------- builder
def hierarchical_form_factors(
    scene: Scene,
    *,
    eta: float = 0.5,
    leaf_size: int = 16,
    occlusion: Literal["auto"] | bool = "auto",
    quadrature_tol: float = 1e-6,
    visibility_samples: int = 3,
    cluster_samples: int = 4,
    order: int = 1,
    error_samples: int = 2000,
    chunk_pairs: int = 1 << 21,
    progress: bool | None = None,
) -> HierarchicalFormFactors:
    """Hierarchical form factors of a (large) scene: exact near field, separable far field (module docstring).

    Args:
        scene: The scene.
        eta: Admissibility: two clusters interact through one far block when ``r_A + r_B ≤ eta·d`` (bounding
            radii against the distance of their centres). Smaller is more accurate and slower
            (benchmarks/results/hierarchical_error.md, ~5,000 facets: relative RMS error of products and row sums
            1.3–1.8 % at eta = 0.5 and 0.30–0.49 % at eta = 0.3, for 1.1–1.15× the time). In a closed, bright
            scene the solved irradiance amplifies row-sum errors by about ``r / (1 − r)``.
        leaf_size: Facets per leaf cluster. Leaf pairs that are not far are evaluated exactly.
        occlusion: ``"auto"`` casts rays only where a third facet could block (near pairs and far blocks);
            ``True`` everywhere, ``False`` never.
        quadrature_tol: Relative accuracy of the near-field quadrature (as ``tol`` of
            :func:`~torch_interreflect.form_factors`).
        visibility_samples: Per-point visibility samples per direction for near pairs (as in the dense kernel).
        cluster_samples: Sample facets per cluster for a far block's visibility: where a third facet could
            block, every facet of each cluster casts ``cluster_samples`` rays to sample facets of the other, and a
            block with any blocked ray is split further (exact near field at leaf level).
        order: Far-field expansion order: 0 (the separable centre-to-centre kernel) or 1 (adds the first-order
            terms in each facet's offset from its cluster centre: about ``eta`` times smaller errors for ~3× the
            cost of a far-field product).
        error_samples: Far-block facet pairs evaluated exactly to estimate the error of a product
            (``info["estimated_rel_error"]``); 0 skips it.
        chunk_pairs: Near-field facet pairs evaluated per chunk (bounds the temporary memory).
        progress: Show progress bars (default: from 5,000 facets).

    Returns:
        A :class:`HierarchicalFormFactors` in the scene's dtype and device. ``info`` holds ``seconds_tree``,
        ``seconds_traversal``, ``seconds_far_visibility``, ``seconds_near``, ``seconds_error_estimate``,
        ``seconds``, ``near_nnz``, ``near_pairs``, ``far_blocks``, ``zero_blocks``, ``rays``, ``bytes``,
        ``estimated_rel_error`` (relative RMS error of ``F @ 1`` estimated from sampled far entries), ...

    Raises:
        TypeError: ``scene`` is not a Scene.
        ValueRangeError: a parameter outside its range.

    Shape:
        - output ``.matmul(x)``: ``[F, K] -> [F, K]``

    Example:
        >>> import torch, torch_interreflect as ti
        >>> scene = ti.scenes.cornell_box(divisions=3, dtype=torch.float64)
        >>> K = ti.hierarchical_form_factors(scene, leaf_size=8)
        >>> E = ti.solve(K, torch.full((scene.num_facets,), 0.5, dtype=torch.float64),
        ...              ti.lights.light_geometry(scene, K, "light")[:, None])
        >>> E.shape
        torch.Size([153, 1])
    """
    _check_arguments(scene, eta, leaf_size, occlusion, quadrature_tol, visibility_samples, cluster_samples, order,
                     error_samples)
    t_all = time.perf_counter()
    F = scene.num_facets
    if progress is None:
        progress = F >= 5000
    sc = scene.to(torch.float64).to("cpu")
    eps = plane_eps(scene)
    info: dict[str, Any] = {"eta": float(eta), "leaf_size": leaf_size, "num_facets": F}

    t = time.perf_counter()
    corners, normals, areas = (t.detach().numpy() for t in (sc.corners, sc.normals, sc.areas))
    tree = build_tree(corners, normals, areas, leaf_size)
    info["seconds_tree"] = time.perf_counter() - t
    info["nodes"] = int(tree.parent.size)

    t = time.perf_counter()
    caster = RayCaster.of(sc) if occlusion is not False else None
    cvis = ClusterVisibility(sc, tree, occlusion, cluster_samples, eps, caster)
    fa, fb, fv, na, nb, stats = traverse(tree, float(eta), eps, cvis, progress)
    info.update(stats)
    info["seconds_traversal"] = time.perf_counter() - t - cvis.seconds
    info["seconds_far_visibility"] = cvis.seconds
    info["far_rays"] = cvis.rays

    t = time.perf_counter()
    near = _near_field(sc, tree, na, nb, occlusion, quadrature_tol, visibility_samples, caster, chunk_pairs,
                       progress, eps, info)
    info["seconds_near"] = time.perf_counter() - t
    info["rays"] = info["near_rays"] + info["far_rays"]

    out = HierarchicalFormFactors(_far_tensors(sc, tree, fa, fb, fv, near), _levels(tree), info, order)
    info["far_blocks"] = out.num_far_blocks

    t = time.perf_counter()
    info["estimated_rel_error"] = _estimate_error(out, sc, tree, fa, fb, error_samples, eps) if (
        error_samples and fa.size) else 0.0
    info["seconds_error_estimate"] = time.perf_counter() - t
    out = out.to(dtype=scene.dtype, device=scene.device)
    info = out.info
    info["bytes"] = out.nbytes()
    info["seconds"] = time.perf_counter() - t_all
    return out


def _check_arguments(scene: Scene, eta: float, leaf_size: int, occlusion: Any, quadrature_tol: float,
                     visibility_samples: int, cluster_samples: int, order: int, error_samples: int) -> None:
    """Raise ``TypeError`` / ``ValueRangeError`` / ``ValueError`` for arguments of the builder out of range."""
    if not isinstance(scene, Scene):
        raise TypeError(f"hierarchical_form_factors expects a Scene; got {type(scene).__name__}")
    if not (isinstance(eta, (int, float)) and 0.0 < eta < 2.0):
        raise ValueRangeError(f"eta must lie in (0, 2) (cluster radii against distance); got {eta!r}")
    check_count(leaf_size, "leaf_size")
    if occlusion not in ("auto", True, False):
        raise ValueError(f"occlusion must be 'auto', True or False; got {occlusion!r}")
    if not (0.0 < quadrature_tol < 1.0):
        raise ValueRangeError(f"quadrature_tol must lie in (0, 1); got {quadrature_tol}")
    for name, val in (("visibility_samples", visibility_samples), ("cluster_samples", cluster_samples)):
        check_count(val, name)
    if order not in (0, 1) or isinstance(order, bool):
        raise ValueRangeError(f"order must be 0 or 1; got {order!r}")
    check_count(error_samples, "error_samples", minimum=0)


def _near_field(sc: Scene, tree: ClusterTree, na: np.ndarray, nb: np.ndarray, occlusion: Any, quadrature_tol: float,
                visibility_samples: int, caster: RayCaster | None, chunk_pairs: int, progress: bool, eps: float,
                info: dict[str, Any]) -> Tensor:
    """Exact ``F_ij`` (float64 sparse CSR ``[F, F]``) of every facet pair of the near leaf pairs ``(na, nb)``.

    Evaluated in chunks of about ``chunk_pairs`` facet pairs by the dense kernel's quadrature; adds
    ``near_pairs``, ``near_nnz``, ``near_leaf_pairs``, ``near_points``, ``near_rays``, ``seconds_near_visibility``
    and ``occluded_facets`` to ``info``.
    """
    F = sc.num_facets
    perm = torch.as_tensor(tree.perm)
    qinfo: dict[str, Any] = {}
    vis = PointVisibility(sc, visibility_samples, caster, angle=VISIBILITY_ANGLE) if caster is not None else None
    rows_l, cols_l, vals_l = [], [], []
    occluded = torch.zeros(F, dtype=torch.bool)
    per_pair = (tree.end[na] - tree.start[na]) * (tree.end[nb] - tree.start[nb])
    n_pairs_total = 0
    bar = tqdm(total=int(per_pair.sum()), desc="near field", unit="pair", leave=False,
               disable=None if progress else True, mininterval=1.0)
    s = 0
    cum = np.cumsum(per_pair)
    while s < na.size:
        # leaf pairs until about chunk_pairs facet pairs
        base = cum[s - 1] if s else 0
        e = max(int(np.searchsorted(cum, base + chunk_pairs, side="right")), s + 1)
        iu, ju = leaf_pairs(tree, na[s:e], nb[s:e])
        bar.update(int(cum[e - 1] - base))
        s = e
        iu, ju = perm[iu], perm[ju]
        iu, ju = torch.minimum(iu, ju), torch.maximum(iu, ju)  # as the dense kernel orders its pairs
        keep = _mutual_facing(sc, iu, ju, eps)
        iu, ju = iu[keep], ju[keep]
        if iu.numel() == 0:
            continue
        n_pairs_total += int(iu.numel())
        dom, tgt, value, need, vis = pair_values(
            sc, iu, ju, occlusion, quadrature_tol, None, visibility_samples, 1 << 18, False, qinfo, eps, vis
        )
        occluded[dom[need]] = True
        occluded[tgt[need]] = True
        rows_l += [dom, tgt]
        cols_l += [tgt, dom]
        vals_l += [value / sc.areas[dom], value / sc.areas[tgt]]
    bar.close()
    if rows_l:
        rows, cols, vals = torch.cat(rows_l), torch.cat(cols_l), torch.cat(vals_l)
        nz = vals > 0
        rows, cols, vals = rows[nz], cols[nz], vals[nz]
    else:
        rows = cols = torch.zeros(0, dtype=torch.int64)
        vals = torch.zeros(0, dtype=torch.float64)
    info.update(near_pairs=n_pairs_total, near_nnz=int(vals.numel()), near_leaf_pairs=int(na.size),
                near_points=qinfo.get("points", 0), near_rays=vis.rays if vis is not None else 0,
                seconds_near_visibility=qinfo.get("seconds_visibility", 0.0), occluded_facets=occluded)
    return sparse_matrix(rows, cols, vals, (F, F), vals.dtype)


def _levels(tree: ClusterTree) -> list[Tensor]:
    """Internal nodes by depth (root first), the order of the operator's upward and downward passes."""
    internal = tree.child[:, 0] >= 0
    levels = [torch.as_tensor(np.nonzero(internal & (tree.depth == d))[0]) for d in range(int(tree.depth.max()) + 1)]
    return [lv for lv in levels if lv.numel()]


def _far_tensors(sc: Scene, tree: ClusterTree, fa: np.ndarray, fb: np.ndarray, fv: np.ndarray,
                 near: Tensor) -> dict[str, Tensor]:
    """The tensors of :class:`HierarchicalFormFactors`: near field, facets, tree links and far blocks (float64)."""
    F = sc.num_facets
    dvec = tree.centre[fb] - tree.centre[fa]
    dist = np.linalg.norm(dvec, axis=1)
    omega = dvec / np.maximum(dist, 1e-300)[:, None]
    coef = fv / (math.pi * dist * dist)
    leaf_of = np.empty(F, dtype=np.int64)
    for lf in np.nonzero(tree.child[:, 0] < 0)[0]:
        leaf_of[tree.start[lf] : tree.end[lf]] = lf
    origin = sc.centroids.detach().mean(0)
    return {
        "near": near, "areas": sc.areas.detach().clone(), "normals": sc.normals.detach().clone(),
        "points": sc.centroids.detach() - origin, "perm": torch.as_tensor(tree.perm),
        "leaf_of": torch.as_tensor(leaf_of), "parent": torch.as_tensor(tree.parent),
        "child": torch.as_tensor(np.where(tree.child < 0, 0, tree.child)),
        "centre": torch.as_tensor(tree.centre) - origin, "block_a": torch.as_tensor(fa),
        "block_b": torch.as_tensor(fb), "omega": torch.as_tensor(omega), "coef": torch.as_tensor(coef),
        "dist": torch.as_tensor(dist),
    }


def _mutual_facing(sc: Scene, i: Tensor, j: Tensor, eps: float) -> Tensor:
    """Some corner of j strictly in front of i's plane and some corner of i in front of j's (the dense cull)."""
    c, n, cent = sc.corners, sc.normals, sc.centroids
    dij = torch.einsum("px,pkx->pk", n[i], c[j]) - (n[i] * cent[i]).sum(-1)[:, None]
    dji = torch.einsum("px,pkx->pk", n[j], c[i]) - (n[j] * cent[j]).sum(-1)[:, None]
    return (dij > eps).any(-1) & (dji > eps).any(-1)


def _estimate_error(K: HierarchicalFormFactors, sc: Scene, tree: ClusterTree, fa: np.ndarray, fb: np.ndarray,
                    samples: int, eps: float) -> float:
    """Relative RMS error of ``F @ 1`` from the far field, estimated by evaluating sampled far entries exactly.

    Blocks are drawn with probability proportional to their share of ``Σ_ij A_i F_ij`` (far), then one facet pair
    per draw; the relative error of those entries (unoccluded, against the dense quadrature) times the far
    share of the row sums estimates the relative error of a product with a smooth vector.
    """
    rng = np.random.default_rng(0)
    areas, normals = sc.areas.detach().numpy(), sc.normals.detach().numpy()
    # block mass: Σ_{i∈a, j∈b} A_i F_ij = c (ω·N_a)(−ω·N_b), N = Σ n_k A_k
    wn = normals * areas[:, None]
    pref = np.concatenate([np.zeros((1, 3)), np.cumsum(wn[tree.perm], axis=0)])
    na_ = pref[tree.end] - pref[tree.start]
    om = K.omega.numpy()
    mass = K.coef.numpy() * (om * na_[fa]).sum(1) * -(om * na_[fb]).sum(1) * 2
    total_far = float(mass.sum())
    if total_far <= 0:
        return 0.0
    pick = rng.choice(fa.size, size=samples, p=mass / total_far)
    ra = rng.integers(tree.start[fa[pick]], tree.end[fa[pick]])
    rb = rng.integers(tree.start[fb[pick]], tree.end[fb[pick]])
    i, j = tree.perm[ra], tree.perm[rb]
    o, d = om[pick], K.dist.numpy()[pick]
    ni, nj = normals[i], normals[j]
    oi, oj = (ni * o).sum(1), (nj * o).sum(1)
    kern = oi * -oj / (math.pi * d * d)
    if K.order >= 1:
        pts, cen = K.points.numpy(), K.centre.numpy()

        def ngn(v: np.ndarray) -> np.ndarray:
            return (-(ni * v).sum(1) * oj - oi * (v * nj).sum(1) + 4 * (o * v).sum(1) * oi * oj) / (math.pi * d**3)

        kern = kern + ngn(pts[j] - cen[fb[pick]]) - ngn(pts[i] - cen[fa[pick]])
    approx = areas[j] * kern
    it, jt = torch.as_tensor(i), torch.as_tensor(j)
    keep = _mutual_facing(sc, it, jt, eps)
    exact = np.zeros(samples)
    if bool(keep.any()):
        _, _, value, _, _ = pair_values(sc, it[keep], jt[keep], False, 1e-4, None, 1, 1 << 18, False, {}, eps)
        # value = A_dom F_dom,tgt; we want F_ij = value / A_i
        exact[keep.numpy()] = value.numpy() / areas[i[keep.numpy()]]
    rel = float(np.sqrt(np.mean((approx - exact) ** 2) / max(np.mean(approx**2), 1e-300)))
    # far share of Σ A_i (F 1)_i
    rs = K.row_sums().numpy()
    total = float((areas * rs).sum())
    share = total_far / total if total > 0 else 0.0
    return float(rel * share)
