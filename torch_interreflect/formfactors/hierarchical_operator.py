"""The operator of the hierarchical kernel: :class:`HierarchicalFormFactors` (exact sparse near field plus separable
far blocks), built by :func:`~torch_interreflect.formfactors.hierarchical_form_factors`."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from ..errors import DeviceError, ShapeError

__all__ = ["HierarchicalFormFactors"]


class HierarchicalFormFactors:
    """Form factors of a large scene as an operator: exact sparse near field plus separable far blocks.

    Built by :func:`hierarchical_form_factors`. It stores no ``[F, F]`` tensor; :meth:`matmul` applies ``F`` in
    ``O(nnz + F + blocks)`` per column, with plain torch operations (any device, float32 or float64).
    ``A_i F_ij = A_j F_ji`` holds exactly (the far blocks are reciprocal by construction), so
    :func:`~torch_interreflect.solve` can use conjugate gradients on the symmetric form.

    Attributes:
        near: Near-field ``F_ij`` (exact quadrature), sparse CSR ``[F, F]`` in the scene's facet order.
        areas: Facet areas in m², ``[F]``.
        normals: Unit facet normals, ``[F, 3]``.
        info: Seconds per stage, near-field nnz, far blocks, rays, bytes used, estimated error of a product.

    Shape:
        - near: ``[F, F]`` (sparse)
        - areas: ``[F]``
        - matmul input/output: ``[..., F, K]``

    Example:
        >>> import torch_interreflect as ti
        >>> K = ti.hierarchical_form_factors(ti.scenes.closed_box(divisions=6), leaf_size=8)
        >>> K.num_facets, K.info["far_blocks"] > 0
        (216, True)
        >>> abs(float(K.row_sums().mean()) - 1.0) < 0.01  # closed box: rows sum to 1 (within the far-field error)
        True
    """

    #: names of the tensors that make up the operator (all moved together by :meth:`to`)
    _NAMES = ("near", "areas", "normals", "points", "perm", "leaf_of", "parent", "child", "centre", "block_a",
              "block_b", "omega", "coef", "dist")

    def __init__(self, tensors: dict[str, Tensor], levels: list[Tensor], info: dict[str, Any], order: int = 1) -> None:
        for k in self._NAMES:
            setattr(self, k, tensors[k])
        # near: CSR F (exact); areas, normals [F]; points: facet centroids relative to the scene centre [F, 3];
        # perm: position -> facet; leaf_of: position -> leaf node; parent/child: tree links (child 0 at leaves);
        # centre: node centres (relative) [nodes, 3]; block_a/b, omega (unit a→b), coef = V/(π d²), dist d [K]
        self.levels = levels  # internal nodes by depth (root first)
        self.order = order
        self.info = info
        self.num_nodes = int(self.parent.numel())

    # ------------------------------------------------------------------ properties
    @property
    def num_facets(self) -> int:
        return int(self.areas.numel())

    @property
    def dtype(self) -> torch.dtype:
        return self.areas.dtype

    @property
    def device(self) -> torch.device:
        return self.areas.device

    @property
    def num_far_blocks(self) -> int:
        return int(self.block_a.numel())

    def _tensors(self) -> dict[str, Tensor]:
        return {k: getattr(self, k) for k in self._NAMES}

    def nbytes(self) -> int:
        """Bytes held by the operator's tensors (near field, far blocks, tree)."""
        total = 0
        for t in [*self._tensors().values(), *self.levels]:
            if t.layout == torch.sparse_csr:
                total += sum(x.numel() * x.element_size() for x in (t.crow_indices(), t.col_indices(), t.values()))
            else:
                total += t.numel() * t.element_size()
        return total

    # ------------------------------------------------------------------ products
    def far_matmul(self, x: Tensor) -> Tensor:
        """The far-field part of ``F @ x`` for ``x`` of shape ``[F, N]``.

        Order 0: ``F_ij ≈ A_j V n_iᵀ W n_j`` with ``W = −ωωᵀ/(π d²)``. Order 1 adds the first-order Taylor terms in
        the positions of both facets about their cluster centres, ``A_j V n_iᵀ (G(δ_j) − G(δ_i)) n_j`` with
        ``G(v) = (−vωᵀ − ωvᵀ + 4(ω·v)ωωᵀ)/(π d³)``, which is still separable (cluster moments ``Σ A_j x_j n_j`` and
        ``Σ A_j x_j δ_j n_jᵀ``) and still reciprocal (``G`` is odd in ω).
        """
        n_cols = x.shape[1]
        dt, dev = x.dtype, x.device
        perm = self.perm
        xp = x[perm]  # positions
        nrm = self.normals[perm]
        w = nrm * self.areas[perm, None]  # [F, 3]
        first = self.order >= 1
        m = torch.zeros(self.num_nodes, 3, n_cols, dtype=dt, device=dev)
        m.index_add_(0, self.leaf_of, w[:, :, None] * xp[:, None, :])
        if first:
            pts = self.points[perm]
            # P = Σ A_j x_j y_j n_jᵀ  [nodes, 3 (y), 3 (n), N]
            p = torch.zeros(self.num_nodes, 3, 3, n_cols, dtype=dt, device=dev)
            p.index_add_(0, self.leaf_of, (pts[:, :, None] * w[:, None, :])[..., None] * xp[:, None, None, :])
        for idx in reversed(self.levels):  # deepest internal nodes first: children are complete
            c0, c1 = self._children_of(idx)
            m[idx] = m[c0] + m[c1]
            if first:
                p[idx] = p[c0] + p[c1]
        t = torch.zeros_like(m)
        q = torch.zeros(self.num_nodes, 3, 3, n_cols, dtype=dt, device=dev) if first else None
        if first:
            s_mom = p - self.centre[:, :, None, None] * m[:, None, :, :]  # Σ A x δ nᵀ, δ = y − c
        chunk = max(1, (1 << 22) // max(9 * n_cols, 1))
        eye = torch.eye(3, dtype=dt, device=dev)
        for s in range(0, self.num_far_blocks, chunk):
            a, b = self.block_a[s : s + chunk], self.block_b[s : s + chunk]
            om, c = self.omega[s : s + chunk], self.coef[s : s + chunk]
            for src, dst, o in ((b, a, om), (a, b, -om)):
                ms = m[src]  # [k, 3, N]
                wm = torch.einsum("kx,kxn->kn", o, ms)  # ω·M
                contrib = o[:, :, None] * (-c[:, None] * wm)[:, None, :]
                if first:
                    kap = (c / self.dist[s : s + chunk])[:, None]  # V / (π d³)
                    sb = s_mom[src]  # [k, 3, 3, N]
                    sw = torch.einsum("kynN,kn->kyN", sb, o)  # S ω
                    tr = sb.diagonal(dim1=1, dim2=2).sum(-1)  # [k, N]
                    wsw = torch.einsum("ky,kyN->kN", o, sw)
                    ca = self.centre[dst]
                    oc = (o * ca).sum(-1)[:, None]  # ω·c_A
                    cm = torch.einsum("kx,kxn->kn", ca, ms)  # c_A·M
                    vec = (-sw - o[:, :, None] * tr[:, None, :] + 4 * o[:, :, None] * wsw[:, None, :]
                           - ca[:, :, None] * wm[:, None, :] - o[:, :, None] * cm[:, None, :]
                           + 4 * (oc * wm)[:, None, :] * o[:, :, None])
                    contrib = contrib + kap[:, :, None] * vec
                    qq = (o[:, :, None, None] * ms[:, None, :, :]
                          + wm[:, None, None, :] * (eye - 4 * o[:, :, None] * o[:, None, :])[..., None])
                    q.index_add_(0, dst, kap[:, :, None, None] * qq)
                t.index_add_(0, dst, contrib)
        for idx in self.levels:  # root first: push every node's field down to its children
            c0, c1 = self._children_of(idx)
            t[c0] += t[idx]
            t[c1] += t[idx]
            if first:
                q[c0] += q[idx]
                q[c1] += q[idx]
        yp = torch.einsum("fx,fxn->fn", nrm, t[self.leaf_of])
        if first:
            yp = yp + torch.einsum("fx,fxyn,fy->fn", nrm, q[self.leaf_of], pts)
        y = torch.empty_like(yp)
        y[perm] = yp
        return y

    def _children_of(self, idx: Tensor) -> tuple[Tensor, Tensor]:
        return self.child[idx, 0], self.child[idx, 1]

    def matmul(self, x: Tensor) -> Tensor:
        """``F @ x`` for ``x`` of shape ``[..., F, K]`` (one pass with all columns); differentiable in ``x``.

        Example:
            >>> import torch, torch_interreflect as ti
            >>> K = ti.hierarchical_form_factors(ti.scenes.closed_box(divisions=3))
            >>> K.matmul(torch.ones(54, 2, dtype=K.dtype)).shape
            torch.Size([54, 2])
        """
        if not isinstance(x, Tensor) or x.ndim < 2 or x.shape[-2] != self.num_facets:
            shape = list(x.shape) if isinstance(x, Tensor) else type(x).__name__
            raise ShapeError(f"x must be a tensor [..., F, K] with F = {self.num_facets} facets; got {shape}")
        if x.device != self.device:
            raise DeviceError(f"x is on {x.device} but the form factors are on {self.device}; move one of them "
                              "with .to(device) (nothing is moved between devices silently)")
        dtype = torch.promote_types(self.dtype, x.dtype) if x.is_floating_point() else self.dtype
        if dtype != self.dtype:  # promote like solve: compute in the wider dtype, return it
            return self._promoted(dtype).matmul(x.to(dtype))
        if x.dtype != dtype:
            x = x.to(dtype)
        lead = x.shape[:-2]
        cols = x.movedim(-2, 0).reshape(self.num_facets, -1)
        out = self.near @ cols + self.far_matmul(cols)
        return out.reshape(self.num_facets, *lead, x.shape[-1]).movedim(0, -2)

    def _promoted(self, dtype: torch.dtype) -> HierarchicalFormFactors:
        """This operator cast to a wider ``dtype`` (cached: repeated products in that dtype cast once)."""
        cache = self.__dict__.setdefault("_promoted_cache", {})
        if dtype not in cache:
            cache[dtype] = self.to(dtype)
        return cache[dtype]

    def rmatmul(self, x: Tensor) -> Tensor:
        """``Fᵀ @ x = A F (x / A)`` (reciprocity) for ``x`` of shape ``[F, N]``."""
        a = self.areas[:, None]
        return a * self.matmul(x / a)

    def row_sums(self) -> Tensor:
        """``Σ_j F_ij`` per facet ``[F]`` (the operator applied to ones; cached)."""
        cached = self.info.get("_row_sums")
        if isinstance(cached, Tensor) and cached.dtype == self.dtype and cached.device == self.device:
            return cached
        rs = self.matmul(torch.ones(self.num_facets, 1, dtype=self.dtype, device=self.device)).reshape(-1)
        self.info["_row_sums"] = rs
        return rs

    def to_dense(self) -> Tensor:
        """The operator as a dense ``[F, F]`` matrix (small scenes and tests only: ``O(F²)`` memory)."""
        return self.matmul(torch.eye(self.num_facets, dtype=self.dtype, device=self.device))

    def to(self, *args: Any, **kwargs: Any) -> HierarchicalFormFactors:
        """Move/cast like :meth:`torch.Tensor.to` (index tensors keep their integer dtype)."""
        probe = torch.empty(0, dtype=self.dtype, device=self.device).to(*args, **kwargs)

        def conv(t: Tensor) -> Tensor:
            return t.to(device=probe.device, dtype=probe.dtype if t.is_floating_point() else t.dtype)

        near = self.near.to(probe.device)
        if near.dtype != probe.dtype:
            near = near.to(probe.dtype)
        info = {k: v for k, v in self.info.items() if k != "_row_sums"}
        tensors = {k: conv(v) for k, v in self._tensors().items() if k != "near"}
        tensors["near"] = near
        return HierarchicalFormFactors(tensors, [conv(t) for t in self.levels], info, self.order)

    def __repr__(self) -> str:
        return (f"HierarchicalFormFactors(num_facets={self.num_facets}, near_nnz={self.info.get('near_nnz')}, "
                f"far_blocks={self.num_far_blocks}, dtype={self.dtype}, device={self.device})")

