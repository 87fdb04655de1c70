"""Random scenes, materials, illuminants, lights and views for synthetic data (deterministic per generator).

Every sampler takes a :class:`numpy.random.Generator` and returns plain Python parameters beside what it builds,
so that a sample's JSON sidecar can say exactly what was drawn. Nothing here depends on global random state:
the same generator state gives the same scene, bit for bit.

Scene kinds (:data:`SCENE_KINDS`), all with a few dozen to about two hundred facets:

- ``"v_groove"``: two plates at a random interior angle (20°–150°) and size (the paper's geometry).
- ``"box_corner"``: three perpendicular squares (a room corner).
- ``"w_shape"``: the paper's W (two valleys and a ridge that hides part of each outer plate).
- ``"cornell"``: a room open on one side (floor, ceiling, back and two side walls) with one or two random blocks.
- ``"mesh"``: concave meshes from trimesh primitives, normals inward: a bowl (half an icosphere), a cup
  (a cylinder without its top cap), an open box; materials by height bands.

Units: metres, nm, K.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

from .. import spectral
from ..errors import SpectralDataError
from ..geometry.scene import Scene
from ..geometry.scenes import box_corner, grid_quads, v_groove, w_shape

__all__ = [
    "ILLUMINANT_KINDS",
    "SCENE_KINDS",
    "random_illuminant",
    "random_light",
    "random_reflectances",
    "random_scene",
    "random_view",
]

#: Scene kinds :func:`random_scene` can draw.
SCENE_KINDS: tuple[str, ...] = ("v_groove", "box_corner", "w_shape", "cornell", "mesh")
#: Illuminant families :func:`random_illuminant` can draw.
ILLUMINANT_KINDS: tuple[str, ...] = ("daylight", "blackbody", "fluorescent")

#: CCT range (K) of the CIE daylights drawn.
DAYLIGHT_CCT = (4000.0, 10000.0)
#: Temperature range (K) of the blackbodies drawn.
BLACKBODY_T = (2500.0, 8000.0)
#: Fluorescent illuminants drawn (CIE F series).
FLUORESCENT = tuple(f"FL{k}" for k in range(1, 13))
#: Reflectances are kept inside this range (a closed room with reflectance 1 never lets light go).
REFLECTANCE_RANGE = (0.02, 0.95)


def _check_kinds(kinds: Sequence[str] | None, allowed: tuple[str, ...], what: str) -> tuple[str, ...]:
    if kinds is None:
        return allowed
    kinds = tuple(kinds)
    bad = [k for k in kinds if k not in allowed]
    if bad or not kinds:
        raise ValueError(f"{what} must be a non-empty list from {list(allowed)}; got {list(kinds)}")
    return kinds


def _u(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(rng.uniform(lo, hi))


# ---------------------------------------------------------------------------------------------------- scenes
def _room(rng: np.random.Generator, dtype: torch.dtype) -> tuple[Scene, dict[str, Any]]:
    w, d, h = _u(rng, 0.8, 1.2), _u(rng, 0.8, 1.2), _u(rng, 0.7, 1.1)
    n = 4
    ex, ey, ez = np.eye(3)
    parts: list[tuple[str, np.ndarray]] = [
        ("floor", grid_quads([0, 0, 0], ex * w, ey * d, n, n)),
        ("ceiling", grid_quads([0, 0, h], ey * d, ex * w, n, n)),
        ("back_wall", grid_quads([0, d, 0], ex * w, ez * h, n, n)),
        ("left_wall", grid_quads([0, 0, 0], ey * d, ez * h, n, n)),
        ("right_wall", grid_quads([w, 0, 0], ez * h, ey * d, n, n)),
    ]
    n_blocks = int(rng.integers(1, 3))
    blocks = []
    for b in range(n_blocks):
        # block b lives in its own half of the floor (left / right), so blocks never intersect
        x_lo, x_hi = (0.0, w / 2) if (n_blocks == 1 or b == 0) else (w / 2, w)
        if n_blocks == 1:
            x_lo, x_hi = 0.0, w
        span = min(x_hi - x_lo, d)
        half = _u(rng, 0.10, 0.22) * span
        hx, hy = half, half * _u(rng, 0.6, 1.0)
        r = math.hypot(hx, hy) * 1.02  # any rotation stays inside this radius
        cx = _u(rng, x_lo + r, x_hi - r) if x_hi - x_lo > 2 * r else (x_lo + x_hi) / 2
        cy = _u(rng, r, d - r)
        height = _u(rng, 0.15, 0.6) * h
        theta = _u(rng, 0.0, math.pi / 2)
        c, s = math.cos(theta), math.sin(theta)
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        X, Y, Z = np.array([2 * hx, 0, 0]), np.array([0, 2 * hy, 0]), np.array([0, 0, height])
        faces = np.concatenate(
            [
                grid_quads([-hx, -hy, height], X, Y, 2, 2),
                grid_quads([hx, -hy, 0], Y, Z, 2, 2),
                grid_quads([-hx, -hy, 0], Z, Y, 2, 2),
                grid_quads([-hx, hy, 0], Z, X, 2, 2),
                grid_quads([-hx, -hy, 0], X, Z, 2, 2),
            ]
        )
        faces = faces @ rot.T + np.array([cx, cy, 0.0])
        parts.append((f"block{b}", faces))
        blocks.append(
            {"centre": [cx, cy], "half_size": [hx, hy], "height": height, "rotation_deg": math.degrees(theta)}
        )
    corners = np.concatenate([p for _, p in parts])
    material = np.concatenate([np.full(len(p), k) for k, (_, p) in enumerate(parts)])
    scene = Scene.from_polygons(torch.as_tensor(corners, dtype=dtype), material=material,
                                material_names=[n for n, _ in parts])
    return scene, {"size": [w, d, h], "divisions": n, "blocks": blocks}


def _concave_mesh(rng: np.random.Generator, dtype: torch.dtype) -> tuple[Scene, dict[str, Any]]:
    import trimesh

    shape = str(rng.choice(["bowl", "cup", "open_box"]))
    scale = _u(rng, 0.05, 0.2)
    aspect = _u(rng, 0.6, 1.4)
    if shape == "bowl":
        mesh = trimesh.creation.icosphere(subdivisions=2)
        cz = mesh.triangles_center[:, 2]
        mesh = trimesh.Trimesh(mesh.vertices, mesh.faces[cz < -0.05], process=False)
        mesh.vertices[:, 2] *= aspect
    elif shape == "cup":
        mesh = trimesh.creation.cylinder(radius=1.0, height=2.0 * aspect, sections=16)
        cz = mesh.triangles_center[:, 2]
        mesh = trimesh.Trimesh(mesh.vertices, mesh.faces[cz < aspect - 1e-6], process=False)  # no top cap
        mesh = mesh.subdivide()
    else:
        mesh = trimesh.creation.box(extents=(2.0, 2.0 * _u(rng, 0.6, 1.0), 2.0 * aspect))
        mesh = mesh.subdivide().subdivide()
        cz = mesh.triangles_center[:, 2]
        mesh = trimesh.Trimesh(mesh.vertices, mesh.faces[cz < aspect - 1e-6], process=False)  # no lid
    mesh.invert()  # normals inward: the concave side reflects
    mesh.apply_scale(scale)
    z = np.asarray(mesh.triangles_center)[:, 2]
    bands = int(rng.integers(2, 4))
    span = max(float(z.max() - z.min()), 1e-12)
    material = np.minimum((bands * (z - z.min()) / span).astype(np.int64), bands - 1)
    scene = Scene(
        torch.as_tensor(np.asarray(mesh.vertices), dtype=dtype),
        torch.as_tensor(np.asarray(mesh.faces, dtype=np.int64)),
        material=material,
        material_names=[f"band{k}" for k in range(bands)],
    )
    return scene, {"shape": shape, "scale": scale, "aspect": aspect, "bands": bands}


def random_scene(
    rng: np.random.Generator, kinds: Sequence[str] | None = None, *, dtype: torch.dtype = torch.float64
) -> tuple[Scene, dict[str, Any]]:
    """A random concave scene of one of ``kinds`` (default: all of :data:`SCENE_KINDS`).

    Args:
        rng: Random generator (the only source of randomness).
        kinds: Scene kinds to choose from, uniformly.
        dtype: Floating dtype of the scene.

    Returns:
        ``(scene, params)``: the scene (with a material index naming its parts) and a JSON-able dict of what
        was drawn (``params["kind"]`` and the kind's own parameters, lengths in metres, angles in degrees).

    Raises:
        ValueError: an unknown kind.

    Example:
        >>> import numpy as np
        >>> from torch_interreflect.training.random_scenes import random_scene
        >>> scene, params = random_scene(np.random.default_rng(0), ["v_groove"])
        >>> params["kind"], scene.num_facets <= 200
        ('v_groove', True)
    """
    kinds = _check_kinds(kinds, SCENE_KINDS, "scene kinds")
    kind = str(kinds[int(rng.integers(len(kinds)))])
    params: dict[str, Any]
    if kind == "v_groove":
        angle = _u(rng, 20.0, 150.0)
        size = (_u(rng, 0.05, 0.15), _u(rng, 0.03, 0.10))
        div = (int(rng.integers(6, 11)), int(rng.integers(6, 11)))
        scene = v_groove(angle, size, div, dtype=dtype)
        params = {"angle_deg": angle, "size": list(size), "divisions": list(div)}
    elif kind == "box_corner":
        size = _u(rng, 0.5, 2.0)
        div = int(rng.integers(5, 9))
        scene = box_corner(size, div, dtype=dtype)
        params = {"size": size, "divisions": div}
    elif kind == "w_shape":
        angle = _u(rng, 30.0, 120.0)
        outer = _u(rng, 0.05, 0.10)
        inner = outer * _u(rng, 0.4, 0.8)
        length = _u(rng, 0.06, 0.12)
        div = (6, 8, 4)
        scene = w_shape(angle, outer, inner, length, div, dtype=dtype)
        params = {"valley_angle_deg": angle, "outer": outer, "inner": inner, "length": length, "divisions": list(div)}
    elif kind == "cornell":
        scene, params = _room(rng, dtype)
    else:
        scene, params = _concave_mesh(rng, dtype)
    return scene, {"kind": kind, **params}


# ---------------------------------------------------------------------------------------------- reflectances
def random_reflectances(
    rng: np.random.Generator,
    num: int,
    data: Tensor,
    basis: tuple[Tensor, Tensor, Tensor],
    *,
    p_measured: float = 0.5,
) -> tuple[Tensor, list[dict[str, Any]]]:
    """``num`` random reflectance spectra: measured ones, or draws from a PCA basis of them.

    Each spectrum is, with probability ``p_measured``, a measured reflectance from ``data`` (colour-science's
    sets, :func:`torch_interreflect.layers.reflectance_data`), else ``mean + Σ_k c_k φ_k`` with
    ``c_k ~ N(0, σ_k²)``, ``σ_k`` the spread of the data along component ``k``. Both are clipped to
    :data:`REFLECTANCE_RANGE`.

    Args:
        rng: Random generator.
        num: Number of spectra.
        data: Measured reflectances. Shape ``[N, L]``.
        basis: ``(mean [L], components [K, L], sigma [K])``.
        p_measured: Probability of a measured spectrum.

    Returns:
        ``(reflectance [num, L], params)``: float64 reflectances and, per spectrum, what was drawn.
    """
    mean, comps, sigma = basis
    out, params = [], []
    for _ in range(int(num)):
        if rng.uniform() < p_measured:
            k = int(rng.integers(data.shape[0]))
            r = data[k].double()
            params.append({"source": "measured", "index": k})
        else:
            c = torch.from_numpy(rng.standard_normal(comps.shape[0])) * sigma.double()
            r = mean.double() + c @ comps.double()
            params.append({"source": "basis", "coefficients": [round(float(v), 6) for v in c]})
        out.append(r.clamp(*REFLECTANCE_RANGE))
    return torch.stack(out), params


# ---------------------------------------------------------------------------------------------- illuminants
def random_illuminant(
    rng: np.random.Generator, wavelengths: Tensor, kinds: Sequence[str] | None = None
) -> tuple[Tensor, dict[str, Any]]:
    """A random illuminant spectrum: CIE daylight (4000–10000 K), blackbody (2500–8000 K) or CIE F1–F12.

    Args:
        rng: Random generator.
        wavelengths: Grid in nm. Shape ``[L]``.
        kinds: Families to choose from, uniformly (default all of :data:`ILLUMINANT_KINDS`).

    Returns:
        ``(spd, params)``: the relative spectrum (float64, as :func:`torch_interreflect.spectral.illuminant`
        gives it, shape ``[L]``) and ``{"kind", "name", "cct"/"temperature"}``.

    Raises:
        ValueError: an unknown kind.
    """
    kinds = _check_kinds(kinds, ILLUMINANT_KINDS, "illuminant kinds")
    kind = str(kinds[int(rng.integers(len(kinds)))])
    wl = wavelengths.double()
    if kind == "daylight":
        cct = _u(rng, *DAYLIGHT_CCT)
        return spectral.illuminant(cct, wl), {"kind": kind, "name": f"D{cct:.0f}K", "cct": cct}
    if kind == "blackbody":
        t = _u(rng, *BLACKBODY_T)
        return spectral.illuminant(f"blackbody:{t!r}", wl), {"kind": kind, "name": f"blackbody:{t:.0f}",
                                                             "temperature": t}
    name = FLUORESCENT[int(rng.integers(len(FLUORESCENT)))]
    try:
        spd = spectral.illuminant(name, wl)
    except SpectralDataError:  # a grid outside the table's 380–780 nm
        spd = spectral.illuminant(name, wl, extrapolate="constant")
    return spd, {"kind": kind, "name": name}


# ---------------------------------------------------------------------------------------------- lights and views
def _mean_normal(scene: Scene) -> np.ndarray:
    n = (scene.normals.double() * scene.areas.double()[:, None]).sum(0).numpy()
    norm = float(np.linalg.norm(n))
    return n / norm if norm > 1e-9 else np.array([0.0, 0.0, 1.0])


def _perturb(rng: np.random.Generator, axis: np.ndarray, max_deg: float) -> np.ndarray:
    """A direction within ``max_deg`` of ``axis`` (uniform on the spherical cap)."""
    axis = axis / np.linalg.norm(axis)
    helper = np.eye(3)[int(np.argmin(np.abs(axis)))]
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    cos_t = 1.0 - rng.uniform() * (1.0 - math.cos(math.radians(max_deg)))
    sin_t = math.sqrt(max(0.0, 1.0 - cos_t**2))
    phi = rng.uniform(0.0, 2.0 * math.pi)
    return cos_t * axis + sin_t * (math.cos(phi) * u + math.sin(phi) * v)


def random_light(rng: np.random.Generator, scene: Scene, row_sums: Tensor) -> tuple[Tensor, dict[str, Any]]:
    """Geometric factor ``g [F]`` of a random light: ``E0 = g ⊗ spectrum``.

    A mixture ``g = a · g_ambient + (1 − a) · g_sun``: the ambient part is uniform (the paper's homogeneous
    light) or a uniform sky (``1 − Σ_j F_ij``, the part of the hemisphere that sees no facet); the sun is a
    directional light within 40° of the scene's mean opening (the area-weighted mean normal), with cast
    shadows. ``a`` is drawn in [0.15, 0.7].

    Args:
        rng: Random generator.
        scene: The scene.
        row_sums: ``Σ_j F_ij`` of its form factors. Shape ``[F]``.

    Returns:
        ``(g [F] float64, params)``.
    """
    from .. import lights

    ambient = "uniform" if rng.uniform() < 0.5 else "sky"
    a = _u(rng, 0.15, 0.7)
    d = -_perturb(rng, _mean_normal(scene), 40.0)  # the direction the light travels
    sc = scene.to(torch.float64)
    g_sun = lights.directional(sc, torch.from_numpy(d), torch.ones(1, dtype=torch.float64))[:, 0]
    g_amb = torch.ones_like(g_sun) if ambient == "uniform" else (1.0 - row_sums.double()).clamp_min(0.0)
    g = a * g_amb + (1.0 - a) * g_sun
    return g, {"ambient": ambient, "ambient_weight": a, "sun_direction": d.tolist()}


def random_view(
    rng: np.random.Generator, scene: Scene, *, fov_range: tuple[float, float] = (35.0, 55.0)
) -> dict[str, Any]:
    """A random pinhole view of the concave side of a scene.

    The camera looks at the centre of the scene's bounding box from a direction within 35° of the mean
    opening (area-weighted mean normal), far enough that the bounding sphere fills 70–100 % of the field of
    view; ``up`` is the world axis least aligned with the viewing direction.

    Args:
        rng: Random generator.
        scene: The scene.
        fov_range: Range of the vertical field of view in degrees.

    Returns:
        ``{"eye": [3], "target": [3], "up": [3], "fov_deg": float}`` (metres, degrees), the arguments of
        :func:`torch_interreflect.imaging.look_at`.
    """
    pts = scene.corners.double().reshape(-1, 3).numpy()
    lo, hi = pts.min(0), pts.max(0)
    centre = (lo + hi) / 2
    radius = float(np.linalg.norm(hi - lo)) / 2
    fov = _u(rng, *fov_range)
    direction = _perturb(rng, _mean_normal(scene), 35.0)
    dist = radius / math.sin(math.radians(fov) / 2) * _u(rng, 0.75, 1.05)
    eye = centre + dist * direction
    target = centre + rng.normal(0.0, 0.05 * radius, 3)
    up = np.eye(3)[int(np.argmin(np.abs(direction)))]
    return {"eye": eye.tolist(), "target": target.tolist(), "up": up.tolist(), "fov_deg": fov}

