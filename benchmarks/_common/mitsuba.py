"""Per-facet irradiance from Mitsuba 3: the independent reference for the speed-against-error benchmark.

Every facet of a :class:`torch_interreflect.Scene` becomes its own Mitsuba mesh (one or two triangles wound
like our corners, so Mitsuba's face normal is our normal) with a one-sided ``diffuse`` BSDF of the facet's
reflectance. The light is a ``directional`` emitter (the sun) or a ``constant`` one (a uniform sky); the
integrator is ``path`` with ``max_depth=-1`` (unbiased infinite bounces with Russian roulette).

Two ways to measure a facet's irradiance, with the same estimator:

* ``mode="sensor"``: an ``irradiancemeter`` sensor is attached to every facet and rendered with
  ``mi.render(scene, sensor=k)``, one facet after the other. This is Mitsuba's own code path end to end.
* ``mode="batched"`` (default): the meter's estimator for all facets in one wavefront. Sample a point on
  the facet (``Shape.sample_position``), a cosine-weighted direction about its normal, start the ray
  ``RayEpsilon`` along that direction (exactly what ``irradiancemeter.sample_ray`` does), trace it with
  the scene's ``path`` integrator and average ``π L`` per facet. It agrees with the sensor mode within
  noise (``python -m benchmarks.mitsuba_ref check``) and runs ~30× faster on small scenes because it
  launches one kernel instead of one per facet, so it is the one we time.

What the meter measures: irradiance on the facet's front side from everything but a delta light. For a
uniform sky that is the whole irradiance. A directional emitter is a delta light that no sensor ray can
hit, so the direct part ``E0 = E_sun max(0, n·(−d))`` is added analytically; the reference scenes lit by
the sun have no cast shadows, which :meth:`MitsubaReference.lit_fraction` checks by casting rays.

Geometry is moved and scaled before it goes to Mitsuba (``scale="auto"``): Mitsuba offsets secondary rays
by ``(1 + max|p|) · 8.9e-5`` along the normal, which at 10 cm scale lifts points near an acute edge behind the
other plate (whose back is black) and loses 2.4 % of the light on the hinge facets of a 30° groove. With the
origin at the bounding box's centre (or at ``origin``, e.g. the middle of the acute edge) and the largest
coordinate scaled to 100, the loss left is ~0.06 % on those facets and ~0.01 % or less elsewhere
(``offset-bias`` measures it). Irradiance from a directional light or a uniform sky does not change with
scale, so results compare directly.

Spectral mode (``variant="llvm_ad_spectral"``): reflectance and light are given per wavelength on a grid
(nm); each path carries 4 wavelengths drawn at the grid's nodes (stratified), so Mitsuba solves exactly the
discrete-wavelength problem the library solves, and the result is ``Σ_λ W_k(λ) E(λ) Δλ`` for weights ``W``
(a camera's sensitivities, per channel). ``mode="sensor"`` in spectral mode uses a ``specfilm`` whose
channels are the weights as step functions over each wavelength's bin, with step-function spectra.

Needs the ``bench`` extra and LLVM for Dr.Jit's LLVM backend::

    apt-get install -y libllvm19          # any LLVM >= 11; set DRJIT_LIBLLVM_PATH if not this one
    .venv/bin/pip install "mitsuba>=3.5"

Sub-commands: ``check`` (closed forms), ``references`` (rebuild the cached references under
``benchmarks/references/``), ``noise`` (error and time against samples per facet), ``offset-bias``, and
``report`` (all three into ``benchmarks/results/speed_vs_error_mitsuba.md``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

os.environ.setdefault("DRJIT_LIBLLVM_PATH", "libLLVM.so.19.1")

HERE = Path(__file__).resolve().parents[1]  # benchmarks/
REFERENCE_DIR = HERE / "references"
RESULTS_DIR = HERE / "results"

#: Paths traced per kernel launch (memory stays small: Mitsuba's loops are symbolic).
MAX_PATHS_PER_PASS = 1 << 22

__all__ = [
    "REFERENCE_DIR",
    "Directional",
    "MitsubaReference",
    "RenderResult",
    "Sky",
    "auto_frame",
    "available",
    "load_mitsuba",
    "load_reference",
    "pilot_and_extend",
    "pooled",
    "reference_names",
    "reference_specs",
    "spectrum_dict",
]


# ---------------------------------------------------------------------------------------------- set-up
def available(variant: str = "llvm_ad_mono") -> bool:
    """Whether Mitsuba 3 imports and offers ``variant`` on this machine."""
    try:
        load_mitsuba(variant)
    except Exception:
        return False
    return True


def load_mitsuba(variant: str) -> Any:
    try:
        import mitsuba as mi
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError(
            "Mitsuba 3 is needed for the reference: `apt-get install -y libllvm19` and "
            "`.venv/bin/pip install 'mitsuba>=3.5'` (the `bench` extra)"
        ) from exc
    if variant not in mi.variants():
        raise ImportError(f"Mitsuba variant {variant!r} is not available; have {mi.variants()}")
    mi.set_variant(variant)
    return mi


# ---------------------------------------------------------------------------------------------- lights
@dataclass(frozen=True)
class Directional:
    """A sun: parallel light travelling along ``direction`` (it is normalised).

    ``irradiance`` is the irradiance on a plane perpendicular to the beam: W·m⁻² in mono, or one value per
    wavelength of the grid (W·m⁻²·nm⁻¹) in spectral mode. Same convention as
    ``ti.lights.directional(scene, direction, spd)``: ``E0_i = E_sun max(0, n_i·(−d))``.
    """

    direction: tuple[float, float, float]
    irradiance: float | tuple[float, ...] = 1.0


@dataclass(frozen=True)
class Sky:
    """A uniform sky (Mitsuba's ``constant`` emitter) of radiance ``radiance`` (W·sr⁻¹·m⁻²(·nm⁻¹)).

    An unoccluded upward facet receives ``π · radiance``.
    """

    radiance: float | tuple[float, ...] = 1.0


Light = Directional | Sky


@dataclass
class RenderResult:
    """Per-facet irradiance from one render.

    Attributes:
        irradiance: ``[F]`` (mono) or ``[F, K]`` (spectral, weighted channels), float64, including the
            analytic direct part of a directional light.
        stderr: Standard error of ``irradiance`` from the per-facet sample variance (same shape).
        spp: Samples (paths) per facet.
        seconds: Wall time of the render (tracing and reductions, not the scene build).
    """

    irradiance: np.ndarray
    stderr: np.ndarray
    spp: int
    seconds: float
    info: dict = field(default_factory=dict)


# ---------------------------------------------------------------------------------------------- scene
def _facets_of(scene: Any) -> tuple[np.ndarray, np.ndarray]:
    """Corners ``[F, 4, 3]`` (float64) and the triangle mask ``[F]`` of a ti.Scene (or a pair of arrays)."""
    if isinstance(scene, tuple):
        corners, tri = scene
    else:
        corners, tri = scene.corners, scene.is_triangle
    corners = np.asarray(corners.detach().cpu().double() if hasattr(corners, "detach") else corners, np.float64)
    tri = np.asarray(tri.cpu() if hasattr(tri, "cpu") else tri, bool)
    if corners.ndim != 3 or corners.shape[1:] != (4, 3):
        raise ValueError(f"corners must have shape [F, 4, 3]; got {list(corners.shape)}")
    return corners, tri


def _normals(corners: np.ndarray) -> np.ndarray:
    n = np.cross(corners[:, 2] - corners[:, 0], corners[:, 3] - corners[:, 1])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def spectrum_dict(value: Any, wavelengths: np.ndarray | None, *, step: bool = False) -> dict:
    """A Mitsuba spectrum dict: a uniform value (mono) or a spectrum on the wavelength grid."""
    v = np.asarray(value, dtype=np.float64)
    if wavelengths is None:
        if v.size != 1:
            raise ValueError(f"mono mode needs one value per facet/light; got shape {list(v.shape)}")
        return {"type": "uniform", "value": float(v.reshape(()))}
    wl = np.asarray(wavelengths, np.float64)
    v = np.broadcast_to(v, wl.shape)
    if not step:
        return {
            "type": "irregular",
            "wavelengths": ", ".join(f"{x:.6f}" for x in wl),
            "values": ", ".join(f"{x:.9g}" for x in v),
        }
    # step function: value v_i on the bin [edge_i, edge_i+1) of node i
    edges = _bin_edges(wl)
    eps = 1e-3
    xs, ys = [], []
    for i in range(len(wl)):
        xs += [edges[i] + (eps if i else 0.0), edges[i + 1] - (eps if i < len(wl) - 1 else 0.0)]
        ys += [v[i], v[i]]
    return {
        "type": "irregular",
        "wavelengths": ", ".join(f"{x:.6f}" for x in xs),
        "values": ", ".join(f"{x:.9g}" for x in ys),
    }


def auto_frame(corners: np.ndarray, origin: Sequence[float] | None = None) -> tuple[np.ndarray, float]:
    """``(centre, factor)`` of ``scale="auto"``: Mitsuba gets ``(p − centre) · factor``, the bounding box's centre
    (or ``origin``) at its origin and the largest coordinate at 100 (see the module docstring)."""
    pts = np.asarray(corners, np.float64).reshape(-1, 3)
    centre = 0.5 * (pts.min(0) + pts.max(0)) if origin is None else np.asarray(origin, np.float64)
    return centre, 100.0 / max(float(np.abs(pts - centre).max()), 1e-300)


def _bin_edges(wl: np.ndarray) -> np.ndarray:
    mid = 0.5 * (wl[1:] + wl[:-1])
    return np.concatenate([[wl[0] - (mid[0] - wl[0])], mid, [wl[-1] + (wl[-1] - mid[-1])]])


def _bin_widths(wl: np.ndarray) -> np.ndarray:
    return np.diff(_bin_edges(np.asarray(wl, np.float64)))


class MitsubaReference:
    """A Mitsuba 3 scene built from our facets, reflectances and light; renders per-facet irradiance.

    Args:
        scene: A ``ti.Scene`` (or ``(corners [F, 4, 3], is_triangle [F])``), metres.
        reflectance: Per-facet reflectance: ``[F]`` or a scalar (mono), ``[F, L]`` or ``[L]`` (spectral).
        light: :class:`Directional` or :class:`Sky`.
        variant: ``"llvm_ad_mono"`` or ``"llvm_ad_spectral"``.
        wavelengths: Wavelength grid ``[L]`` in nm (spectral variants only).
        weights: Spectral only: channel weights ``[K, L]`` (e.g. camera sensitivities) or ``[F, K, L]``;
            the result is ``Σ_λ W_k(λ) E(λ) Δλ`` with ``Δλ`` the bin widths of the grid.
        scale: ``"auto"`` (centre, largest coordinate 100), or a number (multiply, no centring).
        origin: With ``scale="auto"``: the point that goes to Mitsuba's origin (default: the bounding box's
            centre). Mitsuba's ray offset grows with the distance from the origin, so the midpoint of an
            acute edge is a good choice.
        sensors: Also attach an ``irradiancemeter`` per facet (needed for ``mode="sensor"``).
        sampler: Mitsuba sampler plugin for the batched mode (``"independent"`` by default).
        emission: Optional per-facet emitted radiance (``area`` emitters, front side), ``[F]`` or ``[F, L]``;
            used by the closed-form checks (a glowing closed box). ``light`` may then be ``None``.
    """

    def __init__(
        self,
        scene: Any,
        reflectance: Any,
        light: Light,
        *,
        variant: str = "llvm_ad_mono",
        wavelengths: Sequence[float] | np.ndarray | None = None,
        weights: np.ndarray | None = None,
        scale: str | float = "auto",
        sensors: bool = False,
        sampler: str = "independent",
        sensor_spp: int = 1024,
        emission: Any = None,
        origin: Sequence[float] | None = None,
    ) -> None:
        t0 = time.perf_counter()
        self.variant = variant
        self.spectral = "spectral" in variant
        mi = self.mi = load_mitsuba(variant)
        import drjit as dr

        self.dr = dr
        corners, tri = _facets_of(scene)
        F = corners.shape[0]
        self.num_facets = F
        self.normals = _normals(corners)
        self.light = light
        self.sampler_type = sampler
        # --- spectra
        if self.spectral:
            if wavelengths is None:
                raise ValueError("spectral variants need a wavelength grid (nm)")
            self.wavelengths = np.asarray(wavelengths, np.float64)
            L = len(self.wavelengths)
            refl = np.broadcast_to(np.asarray(reflectance, np.float64), (F, L))
            if weights is None:
                weights = np.ones((1, L))
            w = np.asarray(weights, np.float64)
            w = np.broadcast_to(w, (F, *w.shape)) if w.ndim == 2 else w
            if w.shape[0] != F or w.shape[2] != L:
                raise ValueError(f"weights must be [K, L] or [F, K, L] with L={L}; got {list(np.shape(weights))}")
            self.weights = np.ascontiguousarray(w)
            self.num_channels = w.shape[1]
            self.dlambda = _bin_widths(self.wavelengths)
        else:
            if wavelengths is not None:
                raise ValueError("wavelengths are only for spectral variants")
            self.wavelengths = None
            refl = np.broadcast_to(np.asarray(reflectance, np.float64).reshape(-1), (F,))
            self.num_channels = 1
        if refl.min() < 0 or refl.max() > 1:
            raise ValueError(f"reflectance must lie in [0, 1]; got [{refl.min()}, {refl.max()}]")
        self.reflectance = np.array(refl)
        # --- geometry to Mitsuba's frame
        if scale == "auto":
            centre, factor = auto_frame(corners, origin)
        else:
            centre, factor = np.zeros(3), float(scale)
        self.centre, self.scale = centre, factor
        p = (corners - centre) * factor
        self.areas_scaled = 0.5 * np.linalg.norm(np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 1]), axis=1)
        # --- scene dict
        d: dict[str, Any] = {"type": "scene", "integrator": {"type": "path", "max_depth": -1}}
        step = sensors and self.spectral
        if isinstance(light, Sky):
            d["light"] = {"type": "constant", "radiance": spectrum_dict(light.radiance, self.wavelengths, step=step)}
        elif isinstance(light, Directional):
            dvec = np.asarray(light.direction, np.float64)
            dvec = dvec / np.linalg.norm(dvec)
            self.direction = dvec
            d["light"] = {
                "type": "directional",
                "direction": [float(x) for x in dvec],
                "irradiance": spectrum_dict(light.irradiance, self.wavelengths, step=step),
            }
        elif light is not None or emission is None:
            raise TypeError(f"light must be Directional or Sky; got {type(light).__name__}")
        if emission is not None:
            emission = np.broadcast_to(np.asarray(emission, np.float64), refl.shape)
        self.facet_keys = [f"facet_{i:06d}" for i in range(F)]
        for i in range(F):
            props = mi.Properties()
            props["bsdf"] = mi.load_dict(
                {"type": "diffuse", "reflectance": spectrum_dict(refl[i], self.wavelengths, step=step)}
            )
            if sensors:
                props["sensor"] = mi.load_dict(self._sensor_dict(i, sensor_spp))
            if emission is not None and np.any(emission[i] > 0):
                props["emitter"] = mi.load_dict(
                    {"type": "area", "radiance": spectrum_dict(emission[i], self.wavelengths, step=step)}
                )
            nv = 3 if tri[i] else 4
            mesh = mi.Mesh(self.facet_keys[i], nv, nv - 2, props)
            params = mi.traverse(mesh)
            params["vertex_positions"] = mi.Float(np.ascontiguousarray(p[i, :nv], np.float32).ravel())
            faces = [0, 1, 2] if tri[i] else [0, 1, 2, 0, 2, 3]
            params["faces"] = mi.UInt32(np.array(faces, np.uint32))
            params.update()
            d[self.facet_keys[i]] = mesh
        self.scene = mi.load_dict(d)
        # map from the scene's shape order to our facet order
        ids = [s.id() for s in self.scene.shapes()]
        pos = {k: j for j, k in enumerate(ids)}
        order = np.array([pos[k] for k in self.facet_keys], np.uint32)
        self._shape_of_facet = mi.UInt32(order)
        self.build_seconds = time.perf_counter() - t0
        self._check_normals(p)

    # ------------------------------------------------------------------ helpers
    def _sensor_dict(self, i: int, spp: int) -> dict:
        if self.spectral:
            film: dict[str, Any] = {"type": "specfilm", "width": 1, "height": 1, "rfilter": {"type": "box"}}
            for k in range(self.num_channels):
                # the specfilm measures ∫ W(λ) E(λ) dλ: W as a step function of height W_l / Δλ_l on each
                # node's bin gives Σ_l W_l E_l (E is a step function too: every spectrum is given as one)
                band = np.maximum(self.weights[i, k], 0.0)  # tabulated data can hold -1e-19
                film[f"band{k:02d}"] = spectrum_dict(band, self.wavelengths, step=True)
        else:
            film = {"type": "hdrfilm", "width": 1, "height": 1, "rfilter": {"type": "box"}, "pixel_format": "luminance"}
        return {"type": "irradiancemeter", "film": film, "sampler": {"type": self.sampler_type, "sample_count": spp}}

    def _check_normals(self, p: np.ndarray) -> None:
        """Mitsuba's face normal of every facet must be ours."""
        shapes = self.scene.shapes()
        order = np.array(self._shape_of_facet)
        for i in range(self.num_facets):
            n = np.array(shapes[order[i]].face_normal(0)).reshape(-1)
            if float(np.dot(n, self.normals[i])) < 0.999:
                raise RuntimeError(f"facet {i}: Mitsuba normal {n} is not ours {self.normals[i]}")

    def direct(self) -> np.ndarray:
        """Analytic direct irradiance of a directional light ``[F]`` (mono) or ``[F, L]``; zero for a sky."""
        if not isinstance(self.light, Directional):
            shape = (self.num_facets,) if not self.spectral else (self.num_facets, len(self.wavelengths))
            return np.zeros(shape)
        cos = np.clip(self.normals @ (-self.direction), 0.0, None)
        irr = np.asarray(self.light.irradiance, np.float64)
        if self.spectral:
            return cos[:, None] * np.broadcast_to(irr, self.wavelengths.shape)[None, :]
        return cos * float(irr.reshape(()))

    def _direct_weighted(self) -> np.ndarray:
        e0 = self.direct()
        if not self.spectral:
            return e0
        return np.einsum("fkl,fl,l->fk", self.weights, e0, self.dlambda)

    def lit_fraction(self, n: int = 16) -> np.ndarray:
        """Fraction of each facet's sample points (an ``n × n`` grid) that see the sun unblocked ``[F]``.

        Facets facing away from the sun get 0. Used to check that a sun-lit reference has no cast shadows.
        """
        if not isinstance(self.light, Directional):
            raise TypeError("lit_fraction needs a Directional light")
        mi, dr = self.mi, self.dr
        F = self.num_facets
        u = (np.arange(n) + 0.5) / n
        uu, vv = (a.ravel() for a in np.meshgrid(u, u, indexing="ij"))
        idx = np.repeat(np.arange(F, dtype=np.uint32), n * n)
        sample = mi.Point2f(np.tile(uu, F).astype(np.float32), np.tile(vv, F).astype(np.float32))
        sh = dr.gather(mi.ShapePtr, self.scene.shapes_dr(), dr.gather(mi.UInt32, self._shape_of_facet, mi.UInt32(idx)))
        ps = sh.sample_position(0.0, sample)
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.p, si.n = ps.p, ps.n
        ray = si.spawn_ray(mi.Vector3f(*(float(x) for x in -self.direction)))
        blocked = np.array(self.scene.ray_test(ray)).reshape(F, n * n)
        facing = (self.normals @ (-self.direction)) > 0
        return np.where(facing, 1.0 - blocked.mean(1), 0.0)

    # ------------------------------------------------------------------ rendering
    def render(
        self,
        spp: int,
        seed: int = 0,
        *,
        mode: str = "batched",
        part: str = "all",
        sampler: str | None = None,
        max_paths_per_pass: int = MAX_PATHS_PER_PASS,
    ) -> RenderResult:
        """Per-facet irradiance with ``spp`` paths per facet.

        Args:
            spp: Paths per facet.
            seed: Seed; different seeds give independent renders.
            mode: ``"batched"`` (one wavefront for all facets) or ``"sensor"`` (``mi.render`` per facet's
                ``irradiancemeter``; the scene must have been built with ``sensors=True``).
            part: ``"all"``; ``"direct"`` (light seen directly: the analytic sun, or the sky through a
                ``path`` integrator with ``max_depth=1``); ``"indirect"`` (the rest: ``hide_emitters=True``).
                ``direct + indirect = all``; splitting lets a reference spend its samples where the noise is.
            sampler: Mitsuba sampler for this render (default: the one given at construction).
            max_paths_per_pass: Largest wavefront in the batched mode.
        """
        if spp < 1:
            raise ValueError(f"spp must be >= 1; got {spp}")
        if part not in ("all", "direct", "indirect"):
            raise ValueError(f"part must be 'all', 'direct' or 'indirect'; got {part!r}")
        if mode == "batched":
            return self._render_batched(int(spp), int(seed), max_paths_per_pass, part, sampler or self.sampler_type)
        if mode == "sensor":
            if part != "all":
                raise ValueError("mode='sensor' renders part='all' only")
            return self._render_sensors(int(spp), int(seed))
        raise ValueError(f"mode must be 'batched' or 'sensor'; got {mode!r}")

    def render_warm(self, spp: int, seed: int = 0, *, min_time: float = 2.0, **kw: Any) -> RenderResult:
        """Like :meth:`render`, timed without kernel compilation: a render shorter than ``min_time`` (where
        compiling would show) is repeated with seed ``seed + 7919`` and the repeat is returned.

        Dr.Jit compiles a kernel the first time it meets it (the ``multijitter`` sampler bakes the sample count
        in, so each ``spp`` is new) and caches it on disk; a long render hides the compilation anyway.
        """
        r = self.render(spp, seed, **kw)
        if r.seconds < min_time:
            r = self.render(spp, seed + 7919, **kw)
        return r

    def _integrator(self, part: str) -> Any:
        if part == "all":
            return self.scene.integrator()
        cache = self.__dict__.setdefault("_integrators", {})
        if part not in cache:
            d = {"type": "path", "max_depth": 1} if part == "direct" else {"type": "path", "hide_emitters": True}
            cache[part] = self.mi.load_dict(d)
        return cache[part]

    def _render_sensors(self, spp: int, seed: int) -> RenderResult:
        mi = self.mi
        sensors = self.scene.sensors()
        if len(sensors) != self.num_facets:
            raise RuntimeError("build the scene with sensors=True for mode='sensor'")
        # sensors come in the order of their shapes
        order = np.array(self._shape_of_facet)
        K = self.num_channels
        out = np.zeros((self.num_facets, K))
        t0 = time.perf_counter()
        for i in range(self.num_facets):
            img = mi.render(self.scene, sensor=int(order[i]), spp=spp, seed=seed)
            out[i] = np.array(img, np.float64).reshape(-1)[:K]
        seconds = time.perf_counter() - t0
        e = out + self._direct_weighted().reshape(out.shape)
        e = e[:, 0] if not self.spectral else e
        return RenderResult(e, np.full_like(e, np.nan), spp, seconds, {"mode": "sensor"})

    def _render_batched(self, spp: int, seed: int, max_paths: int, part: str, sampler_type: str) -> RenderResult:
        mi = self.mi
        F, K = self.num_facets, self.num_channels
        analytic = isinstance(self.light, Directional)
        info = {"mode": "batched", "sampler": sampler_type, "part": part}
        if part == "direct" and (analytic or self.light is None):
            e = self._direct_weighted().reshape(F, K)
            z = np.zeros_like(e)
            if not self.spectral:
                e, z = e[:, 0], z[:, 0]
            return RenderResult(e, z, spp, 0.0, info)
        integrator = self._integrator("indirect" if (analytic and part == "all") else part)
        spp_pass = max(1, min(spp, max_paths // F))
        if sampler_type != "independent":
            # stratified samplers want a square count per pixel: passes of 4^k samples, spp rounded up
            spp_pass = 4 ** int(math.log(spp_pass, 4) + 1e-9)
            spp = spp_pass * math.ceil(spp / spp_pass)
        n_pass = math.ceil(spp / spp_pass)
        s1 = np.zeros((F, K))
        s2 = np.zeros((F, K))
        done = 0
        t0 = time.perf_counter()
        for k in range(n_pass):
            m = min(spp_pass, spp - done)
            sampler = mi.load_dict({"type": sampler_type, "sample_count": m})
            a, b = self._pass(integrator, sampler, m, (seed * 1_000_003 + k) & 0x7FFFFFFF)
            s1 += a
            s2 += b
            done += m
        seconds = time.perf_counter() - t0
        mean = s1 / spp
        var = np.maximum(s2 / spp - mean**2, 0.0) * spp / max(spp - 1, 1)
        stderr = np.sqrt(var / spp)
        e = mean + (self._direct_weighted().reshape(mean.shape) if analytic and part == "all" else 0.0)
        if not self.spectral:
            e, stderr = e[:, 0], stderr[:, 0]
        info["passes"] = n_pass
        return RenderResult(e, stderr, spp, seconds, info)

    def _pass(self, integrator: Any, sampler: Any, spp: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """One wavefront of ``F * spp`` meter paths; per-facet sums of the estimate and of its square."""
        mi, dr = self.mi, self.dr
        F, K = self.num_facets, self.num_channels
        N = F * spp
        sampler.set_samples_per_wavefront(spp)
        sampler.seed(seed, N)
        facet = dr.arange(mi.UInt32, N) // dr.opaque(mi.UInt32, spp)
        sh = dr.gather(mi.ShapePtr, self.scene.shapes_dr(), dr.gather(mi.UInt32, self._shape_of_facet, facet))
        if self.spectral:
            L = len(self.wavelengths)
            u = sampler.next_1d()
            lanes = []
            for j in range(4):
                uj = u + j / 4.0
                uj = dr.select(uj >= 1.0, uj - 1.0, uj)
                lanes.append(dr.minimum(mi.UInt32(uj * L), L - 1))
            wl_table = mi.Float(self.wavelengths.astype(np.float32))
            wav = [dr.gather(mi.Float, wl_table, b) for b in lanes]
        else:
            wav = None
        ps = sh.sample_position(0.0, sampler.next_2d())
        local = mi.warp.square_to_cosine_hemisphere(sampler.next_2d())
        d = mi.Frame3f(ps.n).to_world(local)
        ray = mi.Ray3f(ps.p + d * mi.math.RayEpsilon, d)
        if wav is not None:
            ray.wavelengths = type(ray.wavelengths)(*wav)
        spec = integrator.sample(self.scene, sampler, ray)[0]
        outs = []
        if self.spectral:
            # estimator of Σ_l W_k(λ_l) E(λ_l) Δλ_l: each lane picks a node uniformly (prob 1/L)
            table = mi.Float((self.weights * self.dlambda[None, None, :]).astype(np.float32).ravel())
            for k in range(K):
                acc = mi.Float(0.0)
                for j in range(4):
                    w = dr.gather(mi.Float, table, (facet * K + k) * L + lanes[j])
                    acc += w * spec[j]
                outs.append(acc * (math.pi * L / 4.0))
        else:
            outs.append(spec[0] * math.pi)
        outs = [mi.Float64(v) for v in outs]  # sum in double: float32 sums of 1e5 terms lose ~1e-5
        sums = [dr.block_sum(v, spp) for v in outs] + [dr.block_sum(v * v, spp) for v in outs]
        dr.eval(*sums)
        arr = [np.array(s, np.float64) for s in sums]
        return np.stack(arr[:K], 1), np.stack(arr[K:], 1)


# ---------------------------------------------------------------------------------------------- references
def _ti() -> Any:
    import torch_interreflect as ti  # late: importing this module needs neither torch nor the library

    return ti


def reference_specs() -> dict[str, dict]:
    """The cached reference scenes: name -> settings (builder, its arguments, light, reflectance).

    Grey reflectance 0.9 ("r9") and 0.2 ("r2") everywhere. Sun-lit scenes have no cast shadows, so the
    direct part is exact and all the Monte Carlo noise is in the interreflections. Irradiance is normalised so
    an unoccluded plane facing the light gets 1 (sun irradiance 1 W/m², or sky radiance 1/π).
    """
    specs: dict[str, dict] = {}
    for r in (0.9, 0.2):
        tag = f"r{round(r * 10)}"
        for angle in (30, 45):
            half = math.radians(angle / 2)
            specs[f"vgroove{angle}_sun_{tag}"] = {
                "builder": "v_groove",
                "kwargs": {"angle_deg": float(angle), "size": [0.09, 0.06], "divisions": 10},
                # the sun along the groove's bisector, into the groove: both plates lit, no cast shadows
                "light": {
                    "type": "directional",
                    "direction": [-math.cos(half), 0.0, -math.sin(half)],
                    "irradiance": 1.0,
                },
                "reflectance": r,
                # Mitsuba's ray offset grows with |p|: put the origin at the middle of the acute hinge
                "mitsuba_origin": [0.0, 0.045, 0.0],
            }
        specs[f"box_corner_sun_{tag}"] = {
            "builder": "box_corner",
            "kwargs": {"size": 1.0, "divisions": 4},
            # down the corner's diagonal: all three faces lit, no cast shadows
            "light": {"type": "directional", "direction": [-1 / math.sqrt(3)] * 3, "irradiance": 1.0},
            "reflectance": r,
        }
        specs[f"w_shape_sun_{tag}"] = {
            "builder": "w_shape",
            "kwargs": {"valley_angle_deg": 45.0, "divisions": [5, 10, 5]},
            # straight down: the profile is monotone in x, so every plate is fully lit; the central ridge
            # still hides parts of the outer plates from each other (occlusion in the interreflections)
            "light": {"type": "directional", "direction": [0.0, 0.0, -1.0], "irradiance": 1.0},
            "reflectance": r,
        }
        specs[f"cornell_sky_{tag}"] = {
            "builder": "cornell_box",
            "kwargs": {"divisions": 1, "light": False},
            # the box is open at the front (z = 0): a uniform sky shines in through the opening
            "light": {"type": "sky", "radiance": 1.0 / math.pi},
            "reflectance": r,
        }
        specs[f"room_sky_{tag}"] = {
            "builder": "room",
            "kwargs": {"divisions": 1.0, "lamp": False, "ceiling": False},
            # a 4 x 5 x 2.6 m room open at the top (a courtyard) with a table, a cabinet and a box: the sky shines
            # in from above; the furniture shadows the floor and stands on it (contacts)
            "light": {"type": "sky", "radiance": 1.0 / math.pi},
            "reflectance": r,
        }
    return specs


def build_scene(spec: dict) -> Any:
    """The ``ti.Scene`` (float64) of a reference spec."""
    ti = _ti()
    import torch

    kw = dict(spec["kwargs"])
    for k in ("size", "divisions"):
        if isinstance(kw.get(k), list):
            kw[k] = tuple(kw[k])
    return getattr(ti.scenes, spec["builder"])(**kw, dtype=torch.float64)


def make_light(d: dict) -> Light:
    if d["type"] == "directional":
        return Directional(tuple(d["direction"]), d["irradiance"])
    if d["type"] == "sky":
        return Sky(d["radiance"])
    raise ValueError(f"unknown light {d!r}")


def reference_names(directory: Path = REFERENCE_DIR) -> list[str]:
    """Names of the cached references present in ``directory``."""
    return sorted(p.stem for p in directory.glob("*.json") if (directory / f"{p.stem}.npz").exists())


def load_reference(name: str, directory: Path = REFERENCE_DIR) -> dict:
    """A cached reference: ``{"irradiance": [F], "noise": [F], "settings": {...}}`` (float64 arrays).

    ``noise`` is the per-facet standard error of ``irradiance`` (absolute); see the JSON for how it was made.
    """
    z = np.load(directory / f"{name}.npz")
    settings = json.loads((directory / f"{name}.json").read_text())
    return {
        "irradiance": z["irradiance"].astype(np.float64),
        "noise": z["noise"].astype(np.float64),
        "render_a": z["render_a"].astype(np.float64),
        "render_b": z["render_b"].astype(np.float64),
        "settings": settings,
    }


def pooled(r0: RenderResult, r1: RenderResult) -> RenderResult:
    """One render from two independent ones of the same quantity: the path-weighted mean, with the standard
    error of that pooled mean, ``sqrt(n0² se0² + n1² se1²) / (n0 + n1)``, and both times added.

    Example:
        >>> import numpy as np
        >>> r = pooled(RenderResult(np.array([1.0]), np.array([0.2]), 100, 1.0),
        ...            RenderResult(np.array([3.0]), np.array([0.1]), 300, 2.0))
        >>> float(r.irradiance[0]), round(float(r.stderr[0]), 6), r.spp
        (2.5, 0.090139, 400)
    """
    n0, n1 = r0.spp, r1.spp
    e = (n0 * r0.irradiance + n1 * r1.irradiance) / (n0 + n1)
    se = np.sqrt(n0**2 * r0.stderr**2 + n1**2 * r1.stderr**2) / (n0 + n1)
    return RenderResult(e, se, n0 + n1, r0.seconds + r1.seconds)


def pilot_and_extend(
    render: Any, num_facets: int, *, target: float, max_paths: float, pilot_spp: int = 16384
) -> tuple[RenderResult, RenderResult, float]:
    """Two independent renders with enough paths for ``target`` relative RMS noise of their mean.

    A pilot pair (seeds 101, 102) measures the error per render at ``pilot_spp``; each is then extended (more
    paths, seeds 1 and 2, :func:`pooled`) to ``spp = pilot_spp (rms_pilot / (√2 target))²``, at most
    ``max_paths`` paths in all.

    Args:
        render: ``render(spp, seed=…) → RenderResult``.
        num_facets: Facets per render (the path budget is per facet).
        target: Relative RMS noise of the mean of the two renders.
        max_paths: Cap on the paths of both renders together.
        pilot_spp: Samples per facet of each pilot render.

    Returns:
        ``(render a, render b, relative RMS error of one pilot render)``.
    """
    pa, pb = render(pilot_spp, seed=101), render(pilot_spp, seed=102)
    pm = 0.5 * (pa.irradiance + pb.irradiance)
    rms_pilot = float(np.sqrt(np.mean(((pa.irradiance - pb.irradiance) / pm) ** 2) / 2))
    spp = int(pilot_spp * (rms_pilot / (math.sqrt(2) * target)) ** 2)
    spp = max(pilot_spp, min(spp, int(max_paths / (2 * num_facets))))

    def extend(r0: RenderResult, seed: int) -> RenderResult:
        # the pilot render plus more paths with another seed: still one unbiased render
        return r0 if spp <= r0.spp else pooled(r0, render(spp - r0.spp, seed=seed))

    return extend(pa, 1), extend(pb, 2), rms_pilot


def make_reference(
    name: str,
    spec: dict,
    *,
    target: float = 3e-4,
    max_paths: float = 8e8,
    pilot_spp: int = 16384,
    directory: Path = REFERENCE_DIR,
) -> dict:
    """Render one reference: two independent renders, enough paths for ``target`` relative RMS noise.

    A pilot pair of renders measures the error per render at ``pilot_spp``; each is then extended (more paths,
    another seed) to ``spp = pilot_spp (rms_pilot / (√2 target))²`` (at most ``max_paths`` paths in all), so
    the mean of the two has relative RMS noise ``target``. The sampler is Mitsuba's ``multijitter`` (stratified:
    at these sample counts ~2.5× less variance than ``independent``, checked to agree within noise).
    """
    import mitsuba as mi

    scene = build_scene(spec)
    light = make_light(spec["light"])
    sampler = "multijitter"
    ref = MitsubaReference(scene, spec["reflectance"], light, sampler=sampler, origin=spec.get("mitsuba_origin"))
    F = ref.num_facets
    if isinstance(light, Directional):
        lit = ref.lit_fraction(24)
        facing = ref.normals @ (-ref.direction) > 0
        if not np.allclose(lit[facing], 1.0):
            raise RuntimeError(f"{name}: the sun casts shadows (lit fraction {lit.min():.3f}); pick another direction")
    t0 = time.perf_counter()
    a, b, rms_pilot = pilot_and_extend(ref.render, F, target=target, max_paths=max_paths, pilot_spp=pilot_spp)
    seconds = time.perf_counter() - t0
    e = 0.5 * (a.irradiance + b.irradiance)
    # |a - b| / 2 estimates the standard error of the mean of the two (one degree of freedom per facet)
    half_diff = 0.5 * np.abs(a.irradiance - b.irradiance)
    rel_two = half_diff / np.abs(e)
    # the sample variance ignores the sampler's stratification: a conservative per-facet standard error
    stderr_iid = 0.5 * np.sqrt(a.stderr**2 + b.stderr**2)
    rms_two = float(np.sqrt(np.mean(rel_two**2)))
    rms_iid = float(np.sqrt(np.mean((stderr_iid / e) ** 2)))
    # per-facet noise: the conservative estimate scaled to the level the two renders measured
    noise = stderr_iid * min(1.0, rms_two / rms_iid)
    directory.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        directory / f"{name}.npz",
        irradiance=e.astype(np.float32),
        noise=noise.astype(np.float32),
        render_a=a.irradiance.astype(np.float32),
        render_b=b.irradiance.astype(np.float32),
    )
    settings = {
        "name": name,
        **spec,
        "num_facets": int(F),
        "renderer": f"Mitsuba {mi.__version__} llvm_ad_mono, path integrator max_depth=-1, irradiancemeter "
        f"estimator batched over facets, sampler {sampler}; scene centred and scaled to max |coordinate| = 100",
        "mitsuba_scale": ref.scale,
        "mitsuba_origin_m": [float(x) for x in ref.centre],
        "spp_per_render": int(a.spp),
        "renders": 2,
        "seeds": [[101, 1], [102, 2]],
        "spp_total": int(a.spp + b.spp),
        "pilot": {"spp": pilot_spp, "rel_rms_error_per_render": rms_pilot},
        "seconds": seconds,
        "rel_noise_rms": rms_two,
        "rel_noise_median": float(np.median(noise / e)),
        "rel_noise_max": float((noise / e).max()),
        "rel_noise_rms_iid_bound": rms_iid,
        "direct": "analytic E_sun max(0, n.(-d)) added (no cast shadows, checked by ray casting)"
        if isinstance(light, Directional)
        else "included in the Monte Carlo estimate (the meter sees the sky)",
        "fields": {
            "irradiance": "mean of the two renders, per facet (float32)",
            "noise": "per-facet standard error of `irradiance`: the sample-variance bound scaled by "
            "rel_noise_rms / rel_noise_rms_iid_bound (the level the two renders measured)",
            "render_a, render_b": "the two independent renders",
        },
    }
    (directory / f"{name}.json").write_text(json.dumps(settings, indent=1) + "\n")
    return settings


# ---------------------------------------------------------------------------------------------- checks
def _unit_square(z: float = 0.0) -> np.ndarray:
    return np.array([[0, 0, z], [1, 0, z], [1, 1, z], [0, 1, z]], np.float64)


def check(spp: int = 1 << 16) -> list[tuple[str, float, float, float]]:
    """Closed-form checks; returns rows ``(name, mitsuba, exact, relative error / standard error)``."""
    rows = []

    def add(name: str, got: float, err: float, exact: float) -> None:
        rows.append((name, got, exact, (got - exact) / err if err > 0 else float("nan")))
        print(f"{name:58s} mitsuba {got:.6f} ± {err:.6f}   exact {exact:.6f}   z = {rows[-1][3]:+.2f}")

    # 1. one upward unit square under a uniform sky of radiance 1: E = π
    one = (_unit_square()[None], np.array([False]))
    r = MitsubaReference(one, 0.5, Sky(1.0)).render(spp, seed=3)
    add("upward square, sky L=1: E = pi", r.irradiance[0], r.stderr[0], math.pi)
    # 2. perpendicular unit squares sharing an edge, black, sky L=1: E = π (1 − F), F = 0.2000438
    floor = _unit_square()
    wall = np.array([[0, 0, 0], [0, 1, 0], [0, 1, 1], [0, 0, 1]], np.float64)  # x = 0, normal +x
    two = (np.stack([floor, wall]), np.array([False, False]))
    r = MitsubaReference(two, 0.0, Sky(1.0)).render(spp, seed=4)
    for i in range(2):
        add(
            f"perpendicular squares, black, sky: E_{i} = pi (1 - F)",
            r.irradiance[i],
            r.stderr[i],
            math.pi * (1 - 0.2000438),
        )
    # 3. same, the sun lights only the wall; floor black, wall reflectance 1: E_floor = F E_wall
    #    (the wall's radiosity is uniform because nothing reflects onto it)
    sun = Directional((-1.0, 0.0, 0.0), 1.0)
    refl = np.array([0.0, 1.0])
    r = MitsubaReference(two, refl, sun).render(spp, seed=5)
    add("perpendicular squares, sun on wall only: E_floor = F", r.irradiance[0], r.stderr[0], 0.2000438)
    # 4. 45° hinge, black, sky: E = π (1 − F_45), F_45 = 0.483348 (Howell C-16)
    c, s = math.cos(math.pi / 4), math.sin(math.pi / 4)
    plate_b = np.array([[0, 0, 0], [0, 1, 0], [c, 1, s], [c, 0, s]], np.float64)  # normal y × d into the groove
    hinge = (np.stack([floor, plate_b]), np.array([False, False]))
    ref = MitsubaReference(hinge, 0.0, Sky(1.0))
    if np.dot(ref.normals[1], [0, 0, -1]) <= 0:
        raise RuntimeError("plate B's normal should point into the groove")
    r = ref.render(spp, seed=6)
    add("45 deg hinge, black, sky: E = pi (1 - 0.483348)", r.irradiance[0], r.stderr[0], math.pi * (1 - 0.483348))
    # 5. infinite bounces: a closed cube whose walls all glow with radiance 1 and reflect r = 0.5 has
    #    radiance 1 / (1 - r) everywhere, so E = 2π on every facet (exact for any closed enclosure)
    ti = _ti()
    box = ti.scenes.closed_box(0.1, divisions=2)
    r = MitsubaReference(box, 0.5, None, emission=1.0).render(max(spp // 64, 256), seed=8)
    e = r.irradiance
    add(
        f"closed glowing box, r=0.5: E = 2 pi (mean of {len(e)})",
        e.mean(),
        r.stderr.mean() / math.sqrt(len(e)),
        2 * math.pi,
    )
    worst = int(np.argmax(np.abs(e - 2 * math.pi)))
    add("closed glowing box, r=0.5: worst facet", e[worst], r.stderr[worst], 2 * math.pi)
    # 6. the batched estimator against Mitsuba's own irradiancemeter + mi.render, per facet
    vg = ti.scenes.v_groove(30.0, divisions=(3, 4))
    sun = Directional((-math.cos(math.radians(15)), 0.0, -math.sin(math.radians(15))), 1.0)
    ref = MitsubaReference(vg, 0.9, sun, sensors=True)
    n = max(spp // 16, 1024)
    a = ref.render(n, seed=9, mode="batched")
    b = ref.render(n, seed=10, mode="sensor")
    z = (b.irradiance - a.irradiance) / (np.sqrt(2) * a.stderr)
    print(
        f"batched vs irradiancemeter sensors, V-groove 30 deg, {vg.num_facets} facets, {n} spp: "
        f"z-scores mean {z.mean():+.2f}, rms {np.sqrt(np.mean(z**2)):.2f}, max |z| {np.abs(z).max():.2f}; "
        f"time batched {a.seconds:.2f} s, sensors {b.seconds:.2f} s"
    )
    rows.append(("batched vs sensor rms z", float(np.sqrt(np.mean(z**2))), 1.0, float(np.abs(z).max())))
    # 7. spectral: an open upward square under a D65 sky, Nikon D5100 channels: ρ_k = π Σ_λ C_k S Δλ
    if available("llvm_ad_spectral"):
        import torch

        wl = ti.spectral.wavelengths(dtype=torch.float64)
        S = (ti.spectral.illuminant("D65", wl) / 100).numpy()
        C = ti.spectral.camera_sensitivities("Nikon 5100 (NPL)", wl).numpy()
        exact = math.pi * (C * S[None] * 10.0).sum(1)
        sref = MitsubaReference(
            one, 0.5, Sky(tuple(S)), variant="llvm_ad_spectral", wavelengths=wl.numpy(), weights=C, sensors=True
        )
        r = sref.render(spp, seed=11)
        for k, ch in enumerate("RGB"):
            add(f"spectral, D65 sky, Nikon {ch}: pi sum C S dl", r.irradiance[0, k], r.stderr[0, k], exact[k])
        rs = sref.render(max(spp // 16, 1024), seed=12, mode="sensor")
        dev = np.abs(rs.irradiance[0] / exact - 1).max()
        print(f"specfilm + irradiancemeter (mi.render): max relative deviation {dev:.1e} at {rs.spp} spp")
        rows.append(("specfilm sensor: max rel. deviation", float(dev), 0.0, float("nan")))
    return rows


def noise_study(
    names: Sequence[str] | None = None,
    spps: Sequence[int] = (64, 256, 1024, 4096, 16384, 65536),
    samplers: Sequence[str] = ("independent", "multijitter"),
) -> list[dict]:
    """Render time and per-facet relative error against the cached references, for several ``spp``."""
    out = []
    for name in names or [n for n in reference_names() if n in reference_specs()]:
        ref = load_reference(name)
        spec = ref["settings"]
        for sampler in samplers:
            m = MitsubaReference(
                build_scene(spec),
                spec["reflectance"],
                make_light(spec["light"]),
                sampler=sampler,
                origin=spec.get("mitsuba_origin"),
            )
            m.render(16, seed=0)  # compile the kernels
            for i, spp in enumerate(spps):
                r = m.render_warm(spp, seed=500 + i)
                rel = (r.irradiance - ref["irradiance"]) / ref["irradiance"]
                row = {
                    "scene": name,
                    "facets": m.num_facets,
                    "sampler": sampler,
                    "spp": r.spp,
                    "seconds": r.seconds,
                    "rel_rmse": float(np.sqrt(np.mean(rel**2))),
                    "rel_max": float(np.abs(rel).max()),
                    # the sample variance's prediction (exact for "independent", an upper bound when stratified)
                    "pred_rel_rmse": float(np.sqrt(np.mean((r.stderr / ref["irradiance"]) ** 2))),
                    "ref_noise": float(spec["rel_noise_rms"]),
                }
                out.append(row)
                print(row, flush=True)
    return out


def offset_bias(names: Sequence[str] | None = None, spp: int = 1 << 16) -> list[dict]:
    """Estimate the bias Mitsuba's ray offsets leave in each reference.

    The same seed (common random numbers) rendered twice: as in the reference, and with the geometry scaled
    so that Mitsuba's offset ``(1 + max|p|) 8.9e-5`` is about twice as large relative to the facets. If the
    error is linear in the offset ``h``, ``E(h) = E* + c h``, then ``E(2h) − E(h) = c h`` is the reference's
    bias; what else is in the difference is the noise of paths that the two offsets send different ways.
    """
    import torch

    out = []
    for name in names or [n for n in reference_names() if n in reference_specs()]:
        ref = load_reference(name)
        spec = ref["settings"]
        scene = build_scene(spec)
        light = make_light(spec["light"])
        a = MitsubaReference(
            scene, spec["reflectance"], light, origin=spec.get("mitsuba_origin"), sampler="multijitter"
        )
        shifted = ((scene.corners - torch.as_tensor(a.centre)).numpy(), scene.is_triangle.numpy())
        half = float(np.abs(shifted[0]).max())
        b = MitsubaReference(shifted, spec["reflectance"], light, scale=2.0 / half, sampler="multijitter")
        ra, rb = a.render(spp, seed=5), b.render(spp, seed=5)
        bias = (rb.irradiance - ra.irradiance) / ref["irradiance"]
        row = {
            "scene": name,
            "scale": [a.scale, b.scale],
            "spp": spp,
            "bias_rms": float(np.sqrt(np.mean(bias**2))),
            "bias_mean": float(bias.mean()),
            "bias_max": float(np.abs(bias).max()),
            "worst_facets": [int(i) for i in np.argsort(-np.abs(bias))[:5]],
        }
        if spec["builder"] == "v_groove":
            n = int(spec["kwargs"]["divisions"])
            cols = bias.reshape(2, n, n).mean(axis=2)  # plate, column (0 at the hinge)
            row["hinge_column_bias"] = float(cols[:, 0].mean())
            row["other_columns_bias_rms"] = float(np.sqrt(np.mean(cols[:, 1:] ** 2)))
        out.append(row)
        print(row, flush=True)
    return out


def write_report(path: Path, checks: list, noise: list[dict], bias: list[dict]) -> None:
    """The Mitsuba side of the benchmark as markdown: closed forms, noise against spp, offset bias."""
    md = [
        "# Mitsuba 3 as the reference: checks, noise and time against samples",
        "",
        "Generated by `benchmarks/mitsuba_ref.py report` (Mitsuba "
        f"{__import__('mitsuba').__version__}, llvm_ad_mono, {os.cpu_count()} CPUs). See `benchmarks/README.md`.",
        "",
        "## Closed forms",
        "",
        "| check | Mitsuba | exact | (Mitsuba − exact) / std. error |",
        "|---|---:|---:|---:|",
    ]
    for name, got, exact, z in checks:
        md.append(f"| {name} | {got:.6f} | {exact:.6f} | {z:+.2f} |")
    md += [
        "",
        "## Noise and time against samples per facet",
        "",
        "Per-facet relative error against the cached reference (whose own noise is in the last column); "
        "*predicted* is the per-facet sample variance's prediction (exact for `independent`, an upper bound for "
        "the stratified `multijitter`). Time is the batched render, without kernel compilation (renders under 2 s "
        "are run twice and timed the second time).",
        "",
        "| scene | facets | sampler | spp | time | rel. RMSE | predicted | max | ref. noise |",
        "|---|---:|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in noise:
        md.append(
            f"| {r['scene']} | {r['facets']} | {r['sampler']} | {r['spp']} | {r['seconds']:.3f} s | "
            f"{100 * r['rel_rmse']:.3f} % | {100 * r['pred_rel_rmse']:.3f} % | {100 * r['rel_max']:.3f} % | "
            f"{100 * r['ref_noise']:.3f} % |"
        )
    md += [
        "",
        "## Bias left by Mitsuba's ray offsets",
        "",
        "Same seed rendered as in the reference and with the offsets about doubled relative to the facets; the "
        "difference estimates the reference's offset bias (plus the noise of paths the two send different ways).",
        "",
        "| scene | spp | bias RMS | bias mean | max | hinge column (V-grooves) | other columns RMS |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in bias:
        hc = f"{100 * r['hinge_column_bias']:+.3f} %" if "hinge_column_bias" in r else "–"
        oc = f"{100 * r['other_columns_bias_rms']:.3f} %" if "other_columns_bias_rms" in r else "–"
        md.append(
            f"| {r['scene']} | {r['spp']} | {100 * r['bias_rms']:.3f} % | {100 * r['bias_mean']:+.3f} % | "
            f"{100 * r['bias_max']:.3f} % | {hc} | {oc} |"
        )
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(md) + "\n")
    print(f"wrote {path}")


def main(argv: Sequence[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("check", help="closed-form checks")
    c.add_argument("--spp", type=int, default=1 << 18)
    sub.add_parser("noise", help="noise and time against spp (needs the cached references)")
    sub.add_parser("offset-bias", help="bias left by Mitsuba's ray offsets in each reference")
    sub.add_parser("report", help="check + noise + offset-bias -> results/speed_vs_error_mitsuba.md")
    m = sub.add_parser("references", help="(re)build the cached references")
    m.add_argument("--target", type=float, default=3e-4, help="relative RMS noise of each reference")
    m.add_argument("--max-paths", type=float, default=8e8, help="cap on paths per reference")
    m.add_argument("--only", nargs="*", default=None)
    a = p.parse_args(argv)
    if a.cmd == "check":
        check(a.spp)
    elif a.cmd == "noise":
        noise_study()
    elif a.cmd == "offset-bias":
        offset_bias()
    elif a.cmd == "report":
        write_report(RESULTS_DIR / "speed_vs_error_mitsuba.md", check(1 << 18), noise_study(), offset_bias())
    elif a.cmd == "references":
        for name, spec in reference_specs().items():
            if a.only and name not in a.only:
                continue
            t = time.perf_counter()
            s = make_reference(name, spec, target=a.target, max_paths=a.max_paths)
            print(
                f"{name}: {s['num_facets']} facets, {s['spp_total']} spp, relative noise rms {s['rel_noise_rms']:.1e}"
                f" median {s['rel_noise_median']:.1e} max {s['rel_noise_max']:.1e}, {time.perf_counter() - t:.0f} s",
                flush=True,
            )


if __name__ == "__main__":
    main()
