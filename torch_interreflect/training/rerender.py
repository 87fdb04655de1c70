"""The image of a known geometry as a function of its illuminant and per-material reflectances, with its Jacobian.

What the geometry refinement (:mod:`.refine`) fits: for a fixed scene (form factors ``F``, light factor ``g``, the
pixels' view of the facets) the camera RGB of every seen pixel is

``p(S, R) = Σ_m  C · (R_m ⊙ Z_m) / π,   Z_m = D_m S + H_m (R_f ⊙ E),   (I − F R_f) E = g ⊗ S``

with ``R_m`` the spectrum of material ``m``, ``R_f`` the facets' reflectances (``R_m`` of their material), ``C`` the
camera's spectral weights, ``H_m`` the pixel × facet gather of the fragments of material ``m`` (dense, ``[N_m, F]``
over the ``N_m`` pixels that hold such fragments) and ``D_m`` their direct light. For a flat image (no gather)
``Z_m = H_m E`` with ``H_m`` the coverage of material ``m``'s facets. This is
:func:`~torch_interreflect.camera.gathered_image` (or ``coverage @ camera(R E / π)``)
regrouped by material, the same to rounding (tested) for the symmetrised form factors below.

:meth:`MaterialImage.jacobian` gives the derivatives of ``p`` along ``P`` directions of ``(S, R)`` at once: the
irradiance tangents ``E_t = (I − F R)^{-1} (F (R_t ⊙ E) + g ⊗ S_t)`` share one Cholesky factor per wavelength (the
symmetric form ``I − R^{1/2} G R^{1/2}``, ``G = A^{1/2} F A^{-1/2}``), and since the model acts per wavelength every
direction is a per-wavelength combination of ``M + 1`` base tangents (the illuminant's and one per material), so the
whole Jacobian costs about one factorisation, ``M + 1`` solves and a few matrix products (2.7× less time than one
tangent per direction on 8 generator samples of 72–192 facets and 60–222 directions, same values to 4e-16).

For infinite bounces ``G`` is symmetrised (``A F`` averaged with its transpose): ``F`` must be reciprocal within
:data:`~torch_interreflect.solver.plan.RECIPROCITY_RTOL`, and the model is that of the symmetrised ``F`` (the
generator's ``F``, reciprocal to 7e-8, moves the image by 8e-10 of its largest pixel). Memory (float64): ``8 N F``
bytes for the per-material gathers (more where pixels mix materials), ``16 L F²`` while factorising,
``8 (M + 1 + 2 P) F L`` for the tangents and ``8 P N 3`` for the Jacobian.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..camera.gather import Gather
from ..camera.sensor import Camera
from ..errors import ShapeError, SingularSystemError, ValueRangeError
from ..formfactors.operator import FormFactors
from ..solver.plan import RECIPROCITY_RTOL

__all__ = ["MaterialImage", "reciprocity_error"]


def reciprocity_error(form_factors: FormFactors) -> float:
    """``max |A_i F_ij − A_j F_ji| / max |A F|`` (0 for an exactly reciprocal ``F``), as the solver measures it."""
    m = form_factors.matrix
    af = form_factors.areas.to(torch.float64)[:, None] * (m.to_dense() if m.layout != torch.strided else m).double()
    top = float(af.abs().max())
    return float((af - af.T).abs().max()) / top if top > 0 else 0.0


class MaterialImage:
    """The seen pixels' camera RGB ``[N, 3]`` of a fixed geometry as a function of ``(S [L], R [M, L])``.

    Args:
        form_factors: The scene's :class:`~torch_interreflect.FormFactors` (for infinite bounces reciprocal within
            :data:`~torch_interreflect.solver.plan.RECIPROCITY_RTOL`).
        light_factor: ``g``, the direct light per facet. Shape ``[F]``.
        material: Material index per facet. Shape ``[F]`` int.
        camera: The :class:`~torch_interreflect.camera.Camera` of the image (its grid has ``L`` wavelengths).
        pixels: For a gathered image, ``(gather, direct)``: the view's
            :class:`~torch_interreflect.camera.gather.Gather` and ``g0`` per fragment ``[K]``
            (:func:`~.refine.gathered_model`); for a flat one, ``None``.
        seen: The pixels kept, ``[H·W]`` bool (row-major); for a flat image with ``pixels=None``, ``coverage``
            must be the coverage of those pixels.
        coverage: Flat image: pixel × facet coverage of the seen pixels ``[N, F]``. Ignored when gathered.
        bounces: ``None`` (infinite) or ``n ≥ 1``: the image of the ``n``-bounce model (as
            :func:`~torch_interreflect.camera.source_irradiance` and the generator for a gathered image, as
            ``solve(..., bounces=n)`` for a flat one).

    Raises:
        ShapeError: sizes that do not agree.
        ValueRangeError: ``bounces`` neither ``None`` nor an integer ≥ 1; for infinite bounces, form factors that
            are not reciprocal within :data:`~torch_interreflect.solver.plan.RECIPROCITY_RTOL`.

    Shape:
        - light_factor, material: ``[F]``
        - coverage: ``[N, F]``; the image: ``[N, 3]`` (``N`` seen pixels, row-major)
    """

    def __init__(self, form_factors: FormFactors, light_factor: Tensor, material: Tensor, camera: Camera,
                 pixels: tuple[Gather, Tensor] | None, seen: Tensor, coverage: Tensor | None = None,
                 bounces: int | None = None) -> None:
        if bounces is not None and (isinstance(bounces, bool) or not isinstance(bounces, int) or bounces < 1):
            raise ValueRangeError(f"MaterialImage: bounces must be None (infinite) or an integer >= 1; got "
                                  f"{bounces!r}")
        dt, dev = torch.float64, light_factor.device
        m = form_factors.matrix
        fm = (m.to_dense() if m.layout != torch.strided else m).to(dt)
        nf = fm.shape[0]
        if light_factor.shape != (nf,) or material.shape != (nf,):
            raise ShapeError(f"light_factor and material must be [F] with F = {nf}; got "
                             f"{list(light_factor.shape)} and {list(material.shape)}")
        if bounces is None:
            err = reciprocity_error(form_factors)
            if err > RECIPROCITY_RTOL:
                raise ValueRangeError(f"MaterialImage: form factors reciprocal within {RECIPROCITY_RTOL:g} expected "
                                      f"(A_i F_ij = A_j F_ji); got a relative violation of {err:.3g}")
        self.num_facets, self.num_materials = nf, int(material.max()) + 1
        self.fm, self.g, self.material = fm, light_factor.to(dt), material.long()
        sa = form_factors.areas.to(dt).sqrt()
        gs = sa[:, None] * fm / sa[None, :]
        self.sa, self.gs = sa, 0.5 * (gs + gs.T)  # reciprocity holds to rounding: the symmetric form
        n_wl = camera.sensitivities.shape[-1]
        eye = torch.eye(n_wl, dtype=camera.sensitivities.dtype, device=camera.sensitivities.device)
        self.cmat = camera(eye).to(device=dev, dtype=dt)  # [L, C]: the camera is linear
        self.gathered = pixels is not None
        onehot = torch.nn.functional.one_hot(self.material, self.num_materials).to(dt)  # [F, M]
        self.onehot = onehot
        if pixels is not None:
            op, direct = pixels
            pf = op.pixel_fragments.to(dt).to_sparse_coo().coalesce()  # [H·W, K], kept sparse
            rows, cols = pf.indices()
            keep = seen.to(rows.device)[rows]
            new_row = torch.cumsum(seen.long(), 0).to(rows.device) - 1
            pf = torch.sparse_coo_tensor(torch.stack([new_row[rows[keep]], cols[keep]]), pf.values()[keep],
                                         (int(seen.sum()), pf.shape[1]), check_invariants=False).coalesce()
            own = onehot[op.fragment_facet.long().to(dev)]  # [K, M]
            gm = op.gather.to(dt).to_dense()  # [K, F]
            share = torch.sparse.mm(pf, own)  # [N, M]: each pixel's weight of each material's fragments
            direct_m = torch.sparse.mm(pf, own * direct.to(dt)[:, None])  # [N, M]
            self.rows = [torch.nonzero(share[:, k] > 0).squeeze(1) for k in range(self.num_materials)]
            self.H = [torch.sparse.mm(pf, own[:, k, None] * gm)[r] for k, r in enumerate(self.rows)]
            self.D = [direct_m[r, k] for k, r in enumerate(self.rows)]
            self.series = None if bounces is None else bounces - 1  # the gather adds the last bounce
        else:
            if coverage is None or coverage.shape[-1] != nf:
                raise ShapeError(f"a flat image needs its coverage [N, F] with F = {nf}")
            cov = coverage.to(dt)
            share = cov @ onehot
            self.rows = [torch.nonzero(share[:, k] > 0).squeeze(1) for k in range(self.num_materials)]
            self.H = [cov[r] * onehot[:, k] for k, r in enumerate(self.rows)]  # [N_k, F]
            self.D = None
            self.series = bounces
        self.num_pixels = share.shape[0]

    # ---------------------------------------------------------------------------------------------- forward
    def _irradiance(self, r_f: Tensor, e0: Tensor) -> tuple[Tensor, tuple[Tensor, Tensor] | None]:
        """``E [F, L]`` of the model (and the Cholesky factors ``[L, F, F]`` with ``R^{1/2}`` when infinite)."""
        if self.series is not None:
            E = torch.zeros_like(e0)
            for _ in range(self.series):
                E = e0 + self.fm @ (r_f * E)
            return E, None
        s = r_f.sqrt().T  # [L, F]
        mat = self.gs.unsqueeze(0) * s.unsqueeze(1)
        mat.mul_(s.unsqueeze(2)).neg_().diagonal(dim1=-2, dim2=-1).add_(1)
        low, info = torch.linalg.cholesky_ex(mat)
        if bool((info > 0).any()):
            raise SingularSystemError("refinement: I − F R is not positive definite (light never leaves the scene)")
        u0 = self.sa[:, None] * e0
        w = torch.cholesky_solve((s.T * u0).T.unsqueeze(-1), low).squeeze(-1)  # [L, F]
        return (u0 + self.gs @ (s.T * w.T)) / self.sa[:, None], (low, s)

    def _pixels(self, refl: Tensor, r_f: Tensor, E: Tensor, spd: Tensor) -> tuple[Tensor, list[Tensor]]:
        """``(p [N, 3], [Z_m [N_m, L]])``: the image and, per material, the light its pixels' fragments receive."""
        src = r_f * E if self.gathered else E
        rc = refl[:, :, None] * self.cmat  # [M, L, 3]
        p = E.new_zeros(self.num_pixels, self.cmat.shape[1])
        zs = []
        for k, (rows, h) in enumerate(zip(self.rows, self.H, strict=True)):
            z = h @ src
            if self.D is not None:
                z = z + self.D[k][:, None] * spd
            p.index_add_(0, rows, z @ rc[k])
            zs.append(z)
        return p / math.pi, zs

    def __call__(self, spd: Tensor, refl: Tensor) -> Tensor:
        """Camera RGB of the seen pixels.

        Args:
            spd: The illuminant ``S`` (as ``E0 = g ⊗ S``). Shape ``[L]``.
            refl: One reflectance per material. Shape ``[M, L]``.

        Returns:
            Shape ``[N, C]`` (``C = 3`` for an RGB camera).

        Raises:
            SingularSystemError: ``I − F R`` not positive definite (infinite bounces).
        """
        r_f = refl[self.material]
        E, _ = self._irradiance(r_f, self.g[:, None] * spd)
        return self._pixels(refl, r_f, E, spd)[0]

    # ---------------------------------------------------------------------------------------------- Jacobian
    def jacobian(self, spd: Tensor, refl: Tensor, spd_t: Tensor, refl_t: Tensor) -> tuple[Tensor, Tensor]:
        """The image and its derivatives along ``P`` directions of ``(S, R)``.

        Args:
            spd, refl: The point, as for :meth:`__call__`.
            spd_t: The directions' parts in ``S``. Shape ``[P, L]``.
            refl_t: Their parts in ``R``. Shape ``[P, M, L]``.

        Returns:
            ``(p, J)``: the image ``[N, C]`` and its derivatives ``[P, N, C]``.

        Raises:
            SingularSystemError: as :meth:`__call__`.
        """
        r_f = refl[self.material]
        e0 = self.g[:, None] * spd
        E, fac = self._irradiance(r_f, e0)
        p, Z = self._pixels(refl, r_f, E, spd)
        r_t = torch.matmul(self.onehot, refl_t)  # [P, F, L]
        E_t = self._tangent(r_f, E, e0, fac, spd_t, refl_t)
        n_p, n_wl = spd_t.shape
        src = r_t * E + r_f * E_t if self.gathered else E_t  # [P, F, L]
        nc = self.cmat.shape[1]
        J = p.new_zeros(p.shape[0], n_p, nc)
        rc = refl[:, :, None] * self.cmat  # [M, L, 3]
        for k, (rows, h) in enumerate(zip(self.rows, self.H, strict=True)):
            w = (refl_t[:, k, :, None] * self.cmat).permute(1, 0, 2).reshape(n_wl, -1)  # [L, P·C]
            jk = Z[k] @ w  # the reflectance at the pixel
            y = (src @ rc[k]).transpose(0, 1).reshape(src.shape[1], -1)  # [F, P·C]
            jk += h @ y  # the light it receives
            if self.D is not None:
                jk += self.D[k][:, None] * (spd_t @ rc[k]).reshape(1, -1)
            J.index_add_(0, rows, jk.reshape(-1, n_p, nc))
        return p, J.transpose(0, 1) / math.pi

    def _tangent(self, r_f: Tensor, E: Tensor, e0: Tensor, fac: tuple[Tensor, Tensor] | None, spd_t: Tensor,
                 refl_t: Tensor) -> Tensor:
        """``E_t [P, F, L]``. The tangent is linear in ``(S_t, R_t)`` and the model acts per wavelength, so every
        direction is ``S_t(λ) T_g + Σ_m R_t,m(λ) T_m`` with ``M + 1`` base tangents: ``T_g`` for ``S_t = 1`` and
        ``T_m`` for ``R_t = 1`` on material ``m``'s facets (cost ``M + 1`` right-hand sides, not ``P``)."""
        m = self.num_materials
        e0_t = torch.zeros(m + 1, *E.shape, dtype=E.dtype, device=E.device)
        e0_t[0] = self.g[:, None]
        r_t = torch.zeros_like(e0_t)
        r_t[1:] = self.onehot.T[:, :, None]
        if fac is None:  # the finite series, differentiated term by term
            Ek, base = torch.zeros_like(E), torch.zeros_like(e0_t)
            for _ in range(self.series or 0):
                base = e0_t + torch.matmul(self.fm, r_t * Ek + r_f * base)
                Ek = e0 + self.fm @ (r_f * Ek)
        else:
            low, s = fac  # the symmetrised model's tangent: A^{1/2} F_sym x = G A^{1/2} x
            u = self.sa[:, None] * e0_t + torch.matmul(self.gs, self.sa[:, None] * (r_t * E))  # [M + 1, F, L]
            w = torch.cholesky_solve((s.T * u).permute(2, 1, 0), low)  # [L, F, M + 1]
            base = (u + torch.matmul(self.gs, s.T * w.permute(2, 1, 0))) / self.sa[:, None]
        coef = torch.cat([spd_t[:, None, :], refl_t], 1)  # [P, M + 1, L]
        return torch.einsum("pjl,jfl->pfl", coef, base)
