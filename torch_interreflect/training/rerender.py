"""The image of a known geometry as a function of its illuminant and per-material reflectances, with its Jacobian.

What the geometry refinement (:mod:`.refine`) fits: for a fixed scene (form factors ``F``, light factor ``g``, the
pixels' view of the facets) the camera RGB of every seen pixel is

``p(S, R) = Σ_m  C · (R_m ⊙ Z_m) / π,   Z_m = D_m S + H_m (R_f ⊙ E),   (I − F R_f) E = g ⊗ S``

with ``R_m`` the spectrum of material ``m``, ``R_f`` the facets' reflectances (``R_m`` of their material), ``C`` the
camera's spectral weights, ``H_m`` the pixel × facet gather of the fragments of material ``m`` (dense, ``[N, F]``)
and ``D_m`` their direct light. For a flat image (no gather) ``Z_m = H_m E`` with ``H_m`` the coverage of material
``m``'s facets. This is :func:`~torch_interreflect.camera.gathered_image` (or ``coverage @ camera(R E / π)``)
regrouped by material, the same to rounding (tested).

:meth:`MaterialImage.jacobian` gives the derivatives of ``p`` along ``P`` directions of ``(S, R)`` at once: the
irradiance tangents ``E_t = (I − F R)^{-1} (F (R_t ⊙ E) + g ⊗ S_t)`` share one Cholesky factor per wavelength (the
symmetric form ``I − R^{1/2} G R^{1/2}``, ``G = A^{1/2} F A^{-1/2}``, as the dense solver), so the whole Jacobian
costs about one factorisation and a few matrix products. Memory: ``8 L F²`` bytes for the factors (float64), ``8 P N
3`` for the Jacobian.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor

from ..camera.sensor import Camera
from ..errors import ShapeError, SingularSystemError

__all__ = ["MaterialImage"]


class MaterialImage:
    """The seen pixels' camera RGB ``[N, 3]`` of a fixed geometry as a function of ``(S [L], R [M, L])``.

    Args:
        form_factors: The scene's :class:`~torch_interreflect.FormFactors` (reciprocal within rounding).
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
    """

    def __init__(self, form_factors: Any, light_factor: Tensor, material: Tensor, camera: Camera,
                 pixels: tuple[Any, Tensor] | None, seen: Tensor, coverage: Tensor | None = None,
                 bounces: int | None = None) -> None:
        dt = torch.float64
        m = form_factors.matrix
        fm = (m.to_dense() if m.layout != torch.strided else m).to(dt)
        nf = fm.shape[0]
        if light_factor.shape != (nf,) or material.shape != (nf,):
            raise ShapeError(f"light_factor and material must be [F] with F = {nf}; got "
                             f"{list(light_factor.shape)} and {list(material.shape)}")
        self.num_facets, self.num_materials = nf, int(material.max()) + 1
        self.fm, self.g, self.material = fm, light_factor.to(dt), material.long()
        sa = form_factors.areas.to(dt).sqrt()
        gs = sa[:, None] * fm / sa[None, :]
        self.sa, self.gs = sa, 0.5 * (gs + gs.T)  # reciprocity holds to rounding: the symmetric form
        n_wl = camera.sensitivities.shape[-1]
        self.cmat = camera(torch.eye(n_wl, dtype=camera.sensitivities.dtype)).to(dt)  # [L, 3]: camera is linear
        self.gathered = pixels is not None
        onehot = torch.nn.functional.one_hot(self.material, self.num_materials).to(dt)  # [F, M]
        self.onehot = onehot
        if pixels is not None:
            op, direct = pixels
            pf = op.pixel_fragments.to(dt).to_dense()[seen]  # [N, K]
            own = onehot[op.fragment_facet.long()]  # [K, M]
            gm = op.gather.to(dt).to_dense()  # [K, F]
            self.H = torch.stack([(pf * own[:, k]) @ gm for k in range(self.num_materials)])  # [M, N, F]
            self.D = pf @ (own * direct.to(dt)[:, None])  # [N, M]
            self.series = None if bounces is None else bounces - 1  # the gather adds the last bounce
        else:
            if coverage is None or coverage.shape[-1] != nf:
                raise ShapeError(f"a flat image needs its coverage [N, F] with F = {nf}")
            cov = coverage.to(dt)
            self.H = torch.stack([cov * onehot[:, k] for k in range(self.num_materials)])  # [M, N, F]
            self.D = None
            self.series = bounces

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

    def _pixels(self, refl: Tensor, r_f: Tensor, E: Tensor, spd: Tensor) -> tuple[Tensor, Tensor]:
        """``(p [N, 3], Z [M, N, L])``."""
        Z = torch.matmul(self.H, r_f * E if self.gathered else E)  # [M, N, L]
        if self.D is not None:
            Z = Z + self.D.T[:, :, None] * spd
        rc = refl[:, :, None] * self.cmat  # [M, L, 3]
        return torch.matmul(Z, rc).sum(0) / math.pi, Z

    def __call__(self, spd: Tensor, refl: Tensor) -> Tensor:
        """Camera RGB of the seen pixels. ``spd [L]``, ``refl [M, L]`` → ``[N, 3]``."""
        r_f = refl[self.material]
        E, _ = self._irradiance(r_f, self.g[:, None] * spd)
        return self._pixels(refl, r_f, E, spd)[0]

    # ---------------------------------------------------------------------------------------------- Jacobian
    def jacobian(self, spd: Tensor, refl: Tensor, spd_t: Tensor, refl_t: Tensor) -> tuple[Tensor, Tensor]:
        """The image and its derivatives along ``P`` directions ``(spd_t [P, L], refl_t [P, M, L])``.

        Returns:
            ``(p [N, 3], J [P, N, 3])``.
        """
        r_f = refl[self.material]
        e0 = self.g[:, None] * spd
        E, fac = self._irradiance(r_f, e0)
        p, Z = self._pixels(refl, r_f, E, spd)
        r_t = torch.matmul(self.onehot, refl_t)  # [P, F, L]
        e0_t = self.g[:, None] * spd_t[:, None, :]
        E_t = self._tangent(r_f, E, e0, e0_t, r_t, fac)
        n_p, n_wl = spd_t.shape
        src = r_t * E + r_f * E_t if self.gathered else E_t  # [P, F, L]
        J = torch.zeros(n_p, p.shape[0], 3, dtype=p.dtype)
        rc = refl[:, :, None] * self.cmat  # [M, L, 3]
        for k in range(self.num_materials):
            w = (refl_t[:, k, :, None] * self.cmat).permute(1, 0, 2).reshape(n_wl, -1)  # [L, P·3]
            J += (Z[k] @ w).reshape(-1, n_p, 3).transpose(0, 1)  # the reflectance at the pixel
            y = (src @ rc[k]).transpose(0, 1).reshape(src.shape[1], -1)  # [F, P·3]
            J += (self.H[k] @ y).reshape(-1, n_p, 3).transpose(0, 1)  # the light it receives
        if self.D is not None:
            J += torch.einsum("nm,pmc->pnc", self.D, torch.einsum("pl,mlc->pmc", spd_t, rc))
        return p, J / math.pi

    def _tangent(self, r_f: Tensor, E: Tensor, e0: Tensor, e0_t: Tensor, r_t: Tensor,
                 fac: tuple[Tensor, Tensor] | None) -> Tensor:
        if fac is None:  # the finite series, differentiated term by term
            Ek, Et = torch.zeros_like(E), torch.zeros_like(e0_t)
            for _ in range(self.series or 0):
                Et = e0_t + torch.matmul(self.fm, r_t * Ek + r_f * Et)
                Ek = e0 + self.fm @ (r_f * Ek)
            return Et
        low, s = fac
        rhs = e0_t + torch.matmul(self.fm, r_t * E)  # [P, F, L]
        u = self.sa[:, None] * rhs
        w = torch.cholesky_solve((s.T * u).permute(2, 1, 0), low)  # [L, F, P]
        return (u + torch.matmul(self.gs, s.T * w.permute(2, 1, 0))) / self.sa[:, None]
