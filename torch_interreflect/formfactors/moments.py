"""Galerkin moments of the kernel on a polynomial basis per facet: the interreflection operator for irradiance that
varies inside a facet (linearly or quadratically) instead of being one constant per facet.

With the orthonormal basis ``ψ_a`` of every facet (:mod:`.basis`; ``ψ_0 = 1``), irradiance is
``E(x) = Σ_a c_{i a} ψ_a(x)`` on facet ``i`` and the Galerkin projection of ``E = E0 + K R E`` is

    c = e0 + G R c,      G[(i, a), (j, b)] = (1 / A_i) ∫_i ψ_a(x) ∫_j k(x, y) V(x, y) ψ_b(y) dA_y dA_x

with ``k = cos θ_x cos θ_y / (π r²)``, ``V`` the visibility and ``e0[(i, a)]`` the mean of ``ψ_a E0`` over ``i``
(:mod:`torch_interreflect.light_moments`). ``G[(i, 0), (j, 0)] = F_ij``: degree 0 is the piecewise-constant model.
Reciprocity holds blockwise, ``A_i G[(i,a),(j,b)] = A_j G[(j,b),(i,a)]``, so the solver's symmetric positive
definite form applies with every facet's area repeated over its basis.

The facet averages ``c_{i 0}`` converge much faster with the degree than with refinement: on a 30° V-groove of
200 facets (r = 0.9, a sun), 1.70 % RMS with constants, 0.23 % with degree 1 and 0.044 % with degree 2, against
degree 2 on the scene subdivided 4 × (README, "Accuracy as an input"; 0.032 % from Mitsuba).

How each pair is integrated (one unordered pair at a time, the smaller facet outside unless a contact along an
edge makes the other the domain, :mod:`.pair_contacts`; reciprocity for the other direction; pairs culled and
classified as in :func:`~torch_interreflect.formfactors.form_factors`):

- near pairs (centroid distance under :data:`RHO_FAR` facet diameters, or touching, or straddling a plane): an outer
  Gauss rule on the domain (graded toward a shared edge or vertex; a domain partly behind the target's plane is
  clipped to it and split in a fan) and, at each point, the inner integral exact in the radius and by
  Gauss-Legendre in the angle (:mod:`._numba_moments`);
- far pairs: a product Gauss rule on both facets (the kernel is smooth there);
- pairs a third facet could block (:func:`~torch_interreflect.formfactors.visibility.blocker_candidates`): the
  unoccluded moments less their blocked part, estimated at every outer point from jittered stratified Embree rays
  to the target (unscaled: an unbiased estimate, see :func:`._numba_moments.pair_moments`).

Not differentiable in the geometry (the moments are computed detached); gradients reach reflectance and light
through :func:`torch_interreflect.solver.solve_moments`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import torch
from torch import Tensor

from .._checks import check_count
from .._threads import caller_threads, compiled_work
from ..errors import ShapeError, ValueRangeError
from ..geometry._polygon import plane_eps
from ..geometry.raycast import RayCaster
from ..geometry.scene import Scene
from .basis import FacetBasis, basis_size, facet_basis
from .compiled import dealt, launch, loops
from .moment_copies import translated_copies
from .moment_reuse import reuse_map, reused_sums
from .operator import FormFactors
from .pair_contacts import CUT_MIN, RuleTable, contacts
from .pairs import classify_pairs, copy_tie, corner_edge_contacts, facing_pairs, order_pairs
from .rules import gauss_legendre, order_for
from .visibility import blocker_candidates

__all__ = ["RHO_FAR", "MomentFormFactors", "mean_moments", "moment_form_factors", "resample_visibility"]

#: Pairs whose centroid distance is at least this many (larger) facet diameters, and that neither touch nor
#: straddle each other's planes, get the product Gauss rule on both facets.
RHO_FAR = 1.0

#: Far pairs' product rule: the order that :func:`~torch_interreflect.formfactors.rules.order_for` gives for this
#: many times the quadrature tolerance (measured: the V-groove's solution moves by < 1e-5 against ``1``).
FAR_TOL_FACTOR = 100.0

#: The far pairs' product rule has at least this many points per side, whatever the degree. Measured on the Cornell
#: box split at its contacts and cut to 0.4 m (no occlusion, r = 0.9, every facet emitting; the largest error of a
#: facet's average against quadrature tol 1e-10): with ``degree + 1`` points, degree 0 was 35 % off at tol 1e-2 and
#: 1e-3, degree 1 0.86 % / 1.1 % / 0.83 % at 1e-2 / 1e-3 / 1e-4; with 3, 0.31 % / 0.090 % / 0.022 % and
#: 0.41 % / 0.10 % / 0.024 % (degree 2, which had 3 already: 0.46 % / 0.13 % / 0.036 %).
FAR_MIN_ORDER = 3

#: Rays cast at once (each is ~ 32 bytes in the buffers).
RAY_CHUNK = 1 << 21

#: ``info`` keys that hold the pairs' sums of :func:`moment_form_factors` (for :func:`resample_visibility` and
#: ``reuse``): not carried over by :meth:`MomentFormFactors.truncate` and :meth:`MomentFormFactors.to`.
_SUMS = ("_sums", "_moment_plan")


def angular_orders(tol: float) -> tuple[int, int]:
    """Gauss points per panel of the inner angular rule: ``(regular, touching)`` pairs for an entry tolerance
    ``tol``. Measured on a 30° V-groove of 200 facets against Lambert's formula (quadrature tol 1e-10): 6 points
    leave 1.1e-7 relative on pairs that do not touch (the outer rule's floor there) and 4.4e-8 on the hinge's
    pairs, 4 points 1.6e-5 and 2.2e-6."""
    digits = max(-math.log10(tol), 1.0)
    regular = int(min(16, max(4, math.ceil(0.8 * digits) + 2)))
    return regular, regular + 2


def angular_panel(tol: float) -> float:
    """Widest panel of the inner angular rule in ``u = asinh(σ / d)`` for an entry tolerance ``tol`` (an edge seen
    across more is split into equal panels; :func:`._numba_contour.inner_exact`).

    Measured (moments of degree 2 without occlusion, the largest relative error of a form factor against quadrature
    tol 1e-10, on grooves of 20° to 150°, the Cornell box and the box split at its contacts and cut to 0.4 m):
    panels 4 wide leave every scene's error as panels 2 wide do at tol 1e-2 and 1e-3 (the outer rule's error
    dominates there) and cost 22 % less CPU in the loops on the cut box at tol 1e-2; at 3e-4 and 1e-4 width 4 is
    2-3× worse on the cut box and width 3 is not; at 1e-5 width 3 is 1.6× worse and at 1e-6 3×."""
    return 4.0 if tol >= 1e-3 else 3.0 if tol >= 1e-4 else 2.0


@dataclass
class MomentFormFactors:
    """The Galerkin moment matrix of a scene on a polynomial basis per facet (see the module docstring).

    Attributes:
        matrix: ``G`` dense ``[F·nb, F·nb]``, rows ``(i, a)`` = ``i·nb + a``, columns likewise (a mean over
            facet ``i`` per row). ``areas``: facet areas ``[F]`` (m²). ``basis``: the :class:`FacetBasis`.
        info: What was computed (pairs of each kind, rays, seconds, tolerance).

    Shape:
        - matrix: ``[F·nb, F·nb]``; areas: ``[F]``
    """

    matrix: Tensor
    areas: Tensor
    basis: FacetBasis
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def num_facets(self) -> int:
        return int(self.areas.shape[0])

    @property
    def degree(self) -> int:
        return self.basis.degree

    @property
    def size(self) -> int:
        """Basis functions per facet (``nb``)."""
        return self.basis.size

    @property
    def dtype(self) -> torch.dtype:
        return self.matrix.dtype

    @property
    def device(self) -> torch.device:
        return self.matrix.device

    def constant(self) -> FormFactors:
        """The degree-0 block: the form factors ``F_ij = G[(i, 0), (j, 0)]`` as :class:`FormFactors`."""
        nb = self.size
        info = {k: v for k, v in self.info.items() if not k.startswith("_")}
        return FormFactors(self.matrix[::nb, ::nb].contiguous(), self.areas, info)

    def truncate(self, degree: int) -> MomentFormFactors:
        """The same moments on the basis of a lower degree (the basis is hierarchical: the leading blocks)."""
        nb_new = basis_size(degree)
        if degree > self.degree:
            raise ValueRangeError(f"degree must be at most {self.degree} (the moments' own); got {degree}")
        if degree == self.degree:
            return self
        F, nb = self.num_facets, self.size
        with caller_threads():  # a copy of most of the matrix: the caller's threads inside compiled_work too
            m = self.matrix.reshape(F, nb, F, nb)[:, :nb_new, :, :nb_new].reshape(F * nb_new, F * nb_new).contiguous()
        b = self.basis
        basis = FacetBasis(degree, b.centroids, b.axes, b.scale, b.transform[:, :nb_new, :nb_new].contiguous())
        info = {k: v for k, v in self.info.items() if k not in _SUMS}
        return MomentFormFactors(m, self.areas, basis, info)

    def to(self, *args: Any, **kwargs: Any) -> MomentFormFactors:
        """Move/cast the matrix and areas like :meth:`torch.Tensor.to` (the basis stays float64 on the CPU)."""
        info = {k: v for k, v in self.info.items() if k not in _SUMS}
        return MomentFormFactors(self.matrix.to(*args, **kwargs), self.areas.to(*args, **kwargs), self.basis, info)

    def __repr__(self) -> str:
        return (f"MomentFormFactors(num_facets={self.num_facets}, degree={self.degree}, size={self.size}, "
                f"dtype={self.dtype}, device={self.device})")


def _kernel() -> Any:
    kern = loops("moments")
    if kern is None:
        raise RuntimeError(
            "moment_form_factors needs its compiled loops (numba), which are disabled (TI_DISABLE_NUMBA=1) or "
            "missing; use form_factors (degree 0) instead"
        )
    return kern


def _pairs(sc: Scene, degree: int, tol: float, eps: float, occlusion: Literal["auto"] | bool,
           tie: float, across: Tensor | None = None) -> dict[str, Any]:
    """The pairs of the moments, each unordered pair once with its domain (the smaller facet, or the one of the
    shorter edge where two edges touch along a line: :func:`~.pairs.corner_edge_contacts`,
    :func:`.pair_contacts.contacts`), its kind (0 exact inner, 1 product Gauss, 2 clipped
    domain), rule, rotation and angular rule, and which pairs need rays; in the arrays the compiled loops take.
    ``exact`` (indexed by ``need_rank``) will hold the occluded pairs' exact unoccluded sums, so their rays can be
    drawn again alone. ``tie`` (:func:`.pairs.copy_tie`): areas that close are a tie for the domain, and ``setup``
    keeps it for :func:`.moment_copies.translated_copies`. ``across``: only the pairs between a facet in this mask
    and one outside it."""
    kern = _kernel()
    iu, ju = facing_pairs(sc, eps, ("dense", 8))
    if across is not None:
        keep = across[iu] != across[ju]
        iu, ju = iu[keep], ju[keep]
    dom, tgt = order_pairs(sc.areas, iu, ju, tie)
    cls = classify_pairs(sc, dom, tgt, tol, None, eps)
    dom, tgt, cls = corner_edge_contacts(sc, dom, tgt, cls)
    radius = (sc.corners - sc.centroids[:, None, :]).norm(dim=-1).amax(1)
    near = (sc.centroids[dom] - sc.centroids[tgt]).norm(dim=-1) <= (radius[dom] + radius[tgt]) * (1 + 1e-6)
    dom, tgt, has_edge, has_vertex, shift, swapped, cut = contacts(
        sc, dom, tgt, cls.has_edge, cls.has_vertex, torch.where(cls.has_edge | cls.has_vertex, cls.shift, 0), near)
    clip_d = torch.where(swapped, cls.clip_t, cls.clip_d)
    clip_t = torch.where(swapped, cls.clip_d, cls.clip_t)
    touch = has_edge | has_vertex
    far = (cls.rho >= RHO_FAR) & ~touch & ~clip_d & ~clip_t
    if occlusion is False or dom.numel() == 0:
        need = torch.zeros(dom.numel(), dtype=torch.bool)
    elif occlusion is True:
        need = torch.ones(dom.numel(), dtype=torch.bool)
    else:
        need = blocker_candidates(sc, dom, tgt, eps)
    order = torch.where(far, order_for(cls.rho, min(0.1, FAR_TOL_FACTOR * tol)).clamp_min(FAR_MIN_ORDER),
                        cls.order).clamp_min(degree + 1)
    kind = torch.where(clip_d, 2, torch.where(far & ~need, 1, 0))  # occluded pairs take the exact inner integral
    rules = RuleTable()
    key = torch.where(has_edge, -1, torch.where(has_vertex, -2, order))
    rule = torch.empty_like(dom)
    for k in torch.unique(key).tolist():
        rid = rules.id("edge", cls.n_adj) if k == -1 else rules.id("vertex", cls.n_adj) if k == -2 else rules.id(
            "plain", k)
        rule[key == k] = rid
    for p in torch.nonzero(has_edge & ((cut[:, 0] > CUT_MIN) | (cut[:, 1] < 1.0 - CUT_MIN))).reshape(-1).tolist():
        ends = tuple(round(float(c), 12) for c in cut[p] if CUT_MIN < float(c) < 1.0 - CUT_MIN)
        rule[p] = rules.id("edge", cls.n_adj, ends)
    edge_rule, vertex_rule = rules.id("edge", cls.n_adj), rules.id("vertex", cls.n_adj)
    off, ru, rv, rw = rules.arrays()
    n_reg, n_fine = angular_orders(tol)
    pairs = [t.contiguous().numpy() for t in (dom, tgt, kind, rule, shift)]
    buf = int(kern.max_points(pairs[2], pairs[3], off, edge_rule, vertex_rule)) if dom.numel() else 1
    nb = basis_size(degree)
    return {"dom": dom, "tgt": tgt, "need": need, "need_rank": np.cumsum(need.numpy()) - 1,
            "exact": np.zeros((int(need.sum()), nb, nb)), "pairs": pairs, "fine": (touch | clip_d).numpy(),
            "rules": (off, ru, rv, rw, edge_rule, vertex_rule), "buf": buf,
            "angular": (*gauss_legendre(n_reg), *gauss_legendre(n_fine),
                        angular_panel(tol)),
            "corners": sc.corners.contiguous().numpy(), "normals": sc.normals.contiguous().numpy(),
            "triangle": sc.is_triangle.cpu().numpy().astype(np.bool_), "scene": sc, "tie": tie}


def _cast(kern: Any, setup: dict[str, Any], sel: np.ndarray, ns: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Rays of the occluded pairs ``sel`` (every outer point to ``ns²`` jittered target samples), cast in chunks of
    whole pairs: each pair's first ray and the blocked flags."""
    counts = np.zeros(sel.size, dtype=np.int64)
    args = (*setup["pairs"], *setup["rules"], setup["corners"], setup["normals"])
    if sel.size:
        launch(kern.count_rays, sel, *args, setup["buf"], counts)
    per = counts * ns * ns
    ray_start = np.zeros(sel.size, dtype=np.int64)
    np.cumsum(per[:-1], out=ray_start[1:])
    blocked = np.zeros(int(per.sum()), dtype=np.bool_)
    if blocked.size == 0:
        return ray_start, blocked
    caster = RayCaster.of(setup["scene"])
    origin = np.asarray(caster.origin, dtype=np.float64)
    tri = setup["triangle"]
    s0 = 0
    while s0 < sel.size:
        s1 = min(sel.size, s0 + max(1, int(np.searchsorted(np.cumsum(per[s0:]), RAY_CHUNK, side="right"))))
        m = int(per[s0:s1].sum())
        ro, rd, rt = np.empty((m, 3), np.float32), np.empty((m, 3), np.float32), np.empty(m, np.float32)
        launch(kern.build_rays, sel[s0:s1], ray_start[s0:s1] - ray_start[s0], *args, tri, ns, seed,
               float(caster.eps), origin, setup["buf"], ro, rd, rt)
        blocked[ray_start[s0]:ray_start[s0] + m] = caster.occluded(ro, rd, rt)
        s0 = s1
    return ray_start, blocked


def moment_form_factors(
    scene: Scene,
    degree: int = 2,
    *,
    quadrature_tol: float = 1e-6,
    occlusion: Literal["auto"] | bool = "auto",
    visibility_samples: int = 3,
    seed: int = 0,
    reuse: tuple[MomentFormFactors, Tensor] | None = None,
    across: Tensor | None = None,
) -> MomentFormFactors:
    """Galerkin moments ``G`` of the interreflection kernel on a polynomial basis of degree ``degree`` per facet.

    Args:
        scene: The scene (any dtype; computed in float64 on the CPU, returned in the scene's dtype and device).
        degree: 0, 1 or 2: total degree of the polynomial that irradiance may have inside every facet.
        quadrature_tol: Relative accuracy per entry that the quadrature orders aim at (outer rule orders from the
            pairs' distance / size ratios, angular rule from :func:`angular_orders`).
        occlusion: ``"auto"`` casts rays only for pairs that a third facet could block; ``False`` never (every pair
            fully visible); ``True`` tests every pair.
        visibility_samples: Rays per side of the target from every outer point of an occluded pair
            (``visibility_samples²`` jittered strata).
        seed: Seed of the jitter (deterministic for a given seed).
        reuse: ``(previous, kept)``: the moments of an earlier scene (straight from this function, with the same
            ``degree``, ``quadrature_tol``, ``occlusion`` and ``visibility_samples``) whose facets ``kept [m]`` are
            this scene's first ``m`` facets, unchanged (a refinement that split the others, as
            :func:`torch_interreflect.accuracy.leaves.split` orders them). A pair of two such facets takes its sums
            from ``previous`` (with its rays) when it needs rays there as here; only the other pairs are integrated.
            The other facets must refine ``previous``'s other facets (checked by their area and bounding box).
            Without occlusion, and with the kept facets in their previous order (as ``split`` keeps them), the
            result is the same as without ``reuse``: bit for bit where no pair is a translated copy of another (in
            another order, or with copies, to rounding).
        across: Only the pairs between a facet in this boolean mask ``[F]`` and one outside it (the others are 0):
            the scene's openings against its facets (:func:`~torch_interreflect.sky_openings.sky_through_openings`).

    Returns:
        :class:`MomentFormFactors` with ``info``: ``pairs``, ``near``/``far``/``clipped`` counts, ``occluded_pairs``,
        ``occluded_facets [F]`` (facets with a ray-cast pair), ``rays``, ``seconds``, ``quadrature_tol``,
        ``reused_pairs`` (pairs taken from ``reuse``), ``copied_pairs`` (pairs that took the sums of a translated
        copy, :func:`.moment_copies.translated_copies`) and ``settings``.

    Raises:
        ValueRangeError: a bad ``degree``, ``quadrature_tol`` or ``visibility_samples``. ShapeError: ``across`` not
            of shape ``[F]``, or given with ``reuse``.
        ValueError: ``reuse`` whose moments do not hold their sums, were made with other settings, or whose
            ``kept`` facets are not this scene's first facets.
        RuntimeError: the compiled loops are disabled (``TI_DISABLE_NUMBA=1``).

    Shape:
        - output ``matrix``: ``[F·nb, F·nb]`` with ``nb = 1, 3, 6`` for degree 0, 1, 2

    Example:
        >>> import torch, torch_interreflect as ti
        >>> scene = ti.scenes.v_groove(90.0, size=(1.0, 1.0), divisions=1, dtype=torch.float64)
        >>> G = ti.formfactors.moment_form_factors(scene, degree=2)
        >>> G.matrix.shape, round(float(G.matrix[0, 6]), 6)    # F_01 of two unit squares at 90°: 0.2000438
        (torch.Size([12, 12]), 0.200044)
    """
    t_start = time.perf_counter()
    nb = basis_size(degree)
    if not (isinstance(quadrature_tol, (int, float)) and not isinstance(quadrature_tol, bool)
            and math.isfinite(quadrature_tol) and 0 < quadrature_tol < 1):
        raise ValueRangeError(f"quadrature_tol must be a number in (0, 1); got {quadrature_tol!r}")
    if occlusion not in ("auto", True, False):
        raise ValueRangeError(f"occlusion must be 'auto', True or False; got {occlusion!r}")
    check_count(visibility_samples, "visibility_samples", note=" (rays per side of the target)")
    if across is not None:
        across = torch.as_tensor(across, dtype=torch.bool)  # a list or an array too
        if tuple(across.shape) != (scene.num_facets,) or reuse is not None:
            raise ShapeError(f"across must be a mask [{scene.num_facets}], without reuse; got {list(across.shape)}"
                             f"{' and reuse' if reuse is not None else ''}")
    with compiled_work():  # torch's glue on one thread, the compiled loops and rays on the caller's
        kern = _kernel()
        sc = scene.to(torch.float64).to("cpu").detach()
        settings = {"degree": int(degree), "quadrature_tol": float(quadrature_tol), "occlusion": occlusion,
                    "visibility_samples": int(visibility_samples)}
        old_of = None if reuse is None else reuse_map(sc, reuse, settings)
        setup = _pairs(sc, degree, quadrature_tol, plane_eps(scene), occlusion, copy_tie(scene.dtype),
                       None if across is None else across.cpu())
        basis = facet_basis(sc, degree)
        acc = np.zeros((setup["dom"].numel(), nb, nb))
        todo = np.arange(acc.shape[0], dtype=np.int64)
        if reuse is not None and old_of is not None:
            todo = reused_sums(setup, reuse[0].info["_sums"][1:], old_of, acc)
        total, copied = _pair_sums(kern, setup, basis, todo, int(visibility_samples), int(seed), acc)
        G = _assemble(kern, sc, setup, basis, acc)
    dom, tgt, need = setup["dom"], setup["tgt"], setup["need"]
    kind = torch.from_numpy(setup["pairs"][2])
    occ_facets = torch.zeros(sc.num_facets, dtype=torch.bool)
    occ_facets[dom[need]] = True
    occ_facets[tgt[need]] = True
    matrix = torch.from_numpy(G).to(dtype=scene.dtype, device=scene.device)
    info = {
        "method": "moments", "degree": int(degree), "quadrature_tol": float(quadrature_tol), "pairs": int(dom.numel()),
        "far": int((kind == 1).sum()), "clipped": int((kind == 2).sum()), "occluded_pairs": int(need.sum()),
        "occluded_facets": occ_facets, "rays": total, "visibility_samples": int(visibility_samples),
        "seconds": time.perf_counter() - t_start, "reused_pairs": int(acc.shape[0] - todo.size),
        "copied_pairs": copied, "settings": settings,
        "_sums": (sc, setup, acc),  # for resample_visibility and reuse: the pairs and their sums
    }
    return MomentFormFactors(matrix, scene.areas.detach().to(scene.dtype), basis, info)


def resample_visibility(moments: MomentFormFactors, *, seed: int, visibility_samples: int | None = None
                        ) -> MomentFormFactors:
    """The same moments with the occluded pairs' rays drawn again (another ``seed``, optionally another
    ``visibility_samples``); the other pairs' sums are reused, and of the occluded pairs only the blocked part is
    evaluated (their exact unoccluded sums are kept), so this costs the rays alone. The change
    between the two measures the sampled visibility's error (:mod:`torch_interreflect.accuracy.moments_plan`).

    Raises:
        ValueError: ``moments`` does not hold the sums of :func:`moment_form_factors` (e.g. after ``.to()``).
    """
    sums = moments.info.get("_sums")
    if sums is None:
        raise ValueError("resample_visibility needs moments straight from moment_form_factors (they keep their "
                         "pairs' sums); got moments without them")
    sc, setup, acc = sums
    ns = int(visibility_samples if visibility_samples is not None else moments.info["visibility_samples"])
    check_count(ns, "visibility_samples", note=" (rays per side of the target)")
    t0 = time.perf_counter()
    kern = _kernel()
    sel = dealt(torch.nonzero(setup["need"]).reshape(-1).numpy().astype(np.int64))
    acc = acc.copy()
    ray_start, blocked = _cast(kern, setup, sel, ns, int(seed))
    part = np.zeros((sel.size, moments.basis.size, moments.basis.size))
    if sel.size:
        launch(kern.blocked_moments, sel, ray_start, *setup["pairs"], *setup["rules"], setup["corners"],
               setup["normals"], *_frames(moments.basis), setup["triangle"], int(moments.basis.degree), setup["buf"],
               blocked, ns, int(seed), part)
        acc[sel] = setup["exact"][setup["need_rank"][sel]] - part
    rays = int(blocked.size)
    G = _assemble(kern, sc, setup, moments.basis, acc, base=moments.matrix)
    settings = dict(moments.info.get("settings", {}), visibility_samples=ns)
    info = dict(moments.info, rays=rays, visibility_samples=ns, seconds=time.perf_counter() - t0,
                _sums=(sc, setup, acc), settings=settings, reused_pairs=0)
    info.pop("_moment_plan", None)
    matrix = torch.from_numpy(G).to(dtype=moments.dtype, device=moments.device)
    return MomentFormFactors(matrix, moments.areas, moments.basis, info)


def mean_moments(a: MomentFormFactors, b: MomentFormFactors) -> MomentFormFactors:
    """The average of two replicas of the same moments (:func:`resample_visibility` of one another with other seeds):
    every pair's sums averaged, so the occluded pairs' unbiased estimates hold the rays of both (the other pairs are
    the same in both). The light of the mean is the mean of the lights (the moments enter it linearly).

    Raises:
        ValueError: ``a`` and ``b`` are not replicas (other pairs, or other visibility sample counts).
    """
    sa, sb = a.info.get("_sums"), b.info.get("_sums")
    if sa is None or sb is None or sa[1] is not sb[1] or a.info.get("settings") != b.info.get("settings"):
        raise ValueError("mean_moments needs two replicas of the same moments (resample_visibility of one another, "
                         "with the same visibility_samples); got moments of other pairs or settings")
    sc, setup, acc = sa[0], sa[1], 0.5 * (sa[2] + sb[2])
    G = _assemble(_kernel(), sc, setup, a.basis, acc, base=a.matrix)
    info = dict(a.info, rays=int(a.info["rays"]) + int(b.info["rays"]), _sums=(sc, setup, acc))
    info.pop("_moment_plan", None)
    return MomentFormFactors(torch.from_numpy(G).to(dtype=a.dtype, device=a.device), a.areas, a.basis, info)


def _pair_sums(kern: Any, setup: dict[str, Any], basis: FacetBasis, todo: np.ndarray, ns: int, seed: int,
               acc: np.ndarray) -> tuple[int, int]:
    """Fill ``acc[todo]`` with the pairs' monomial sums (rays cast for the occluded ones among them, whose exact
    unoccluded sums go to ``setup["exact"]``); the ray count and the number of copied pairs. One pair of each class
    of translated copies is integrated (:func:`.moment_copies.translated_copies`), dealt to the threads
    (:func:`dealt`); the others take its exact sums, less their own blocked part where they are occluded."""
    need = setup["need"].numpy()
    rep = translated_copies(kern, setup, todo)
    is_copy = rep != todo
    own = dealt(todo[~is_copy])
    spread = dealt(todo)
    sel = spread[need[spread]]
    sel_of = np.full(setup["dom"].numel(), -1, dtype=np.int64)
    sel_of[sel] = np.arange(sel.size)
    ray_start, blocked = _cast(kern, setup, sel, ns, seed)
    tri = setup["triangle"]
    exact = np.zeros((max(1, sel.size), basis.size, basis.size))
    frames = _frames(basis)
    if own.size:
        launch(kern.pair_moments, own, *setup["pairs"], setup["fine"], *setup["rules"], setup["corners"],
               setup["normals"], *frames, tri, int(basis.degree), *setup["angular"], setup["buf"], sel_of,
               ray_start, blocked, ns, seed, acc, exact)
    copies = todo[is_copy]
    if copies.size:
        src = rep[is_copy]
        occluded_src = sel_of[src] >= 0  # an occluded class's exact sums are in `exact`, not in `acc`
        acc[copies] = acc[src]
        acc[copies[occluded_src]] = exact[sel_of[src[occluded_src]]]
        hit = dealt(copies[need[copies]])
        if hit.size:
            exact[sel_of[hit]] = acc[hit]
            part = np.zeros((hit.size, basis.size, basis.size))
            launch(kern.blocked_moments, hit, ray_start[sel_of[hit]], *setup["pairs"], *setup["rules"],
                   setup["corners"], setup["normals"], *frames, tri, int(basis.degree), setup["buf"], blocked, ns,
                   seed, part)
            acc[hit] = acc[hit] - part
    if sel.size:
        setup["exact"][setup["need_rank"][sel]] = exact[:sel.size]
    return int(blocked.size), int(copies.size)


def _frames(basis: FacetBasis) -> tuple[np.ndarray, ...]:
    """Each facet's frame for the compiled loops: centroids, the two axes and one over the scale."""
    return (basis.centroids.numpy(), basis.axes[:, 0].contiguous().numpy(), basis.axes[:, 1].contiguous().numpy(),
            (1.0 / basis.scale).numpy())


def _assemble(kern: Any, sc: Scene, setup: dict[str, Any], basis: FacetBasis, acc: np.ndarray,
              base: Tensor | None = None) -> np.ndarray:
    """The dense matrix ``[F·nb, F·nb]`` from the pairs' sums; with ``base`` (a matrix of the same pairs whose
    occluded pairs' sums alone differ) a copy of it with only the occluded pairs' blocks written again."""
    F, nb = sc.num_facets, basis.size
    if base is None:
        G = np.zeros((F * nb, F * nb))
        sel = slice(None)
    else:
        with caller_threads():  # the whole matrix copied: on the caller's threads inside compiled_work too
            G = base.detach().to("cpu", torch.float64, copy=True).numpy()
        sel = setup["need"].numpy()
    if acc.shape[0]:
        launch(kern.scatter_blocks, np.ascontiguousarray(setup["pairs"][0][sel]),
               np.ascontiguousarray(setup["pairs"][1][sel]), np.ascontiguousarray(acc[sel]),
               basis.transform.numpy(), sc.areas.numpy(), G)
    return G
