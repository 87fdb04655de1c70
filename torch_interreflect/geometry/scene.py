"""Scenes: planar convex facets (triangles and quads) held as tensors.

A :class:`Scene` stores every facet as four corners ``[F, 4, 3]``; a triangle repeats its last vertex
(``corners[i, 3] == corners[i, 2]``), so triangles and quads share one code path (the bilinear map of such a
collapsed quad is the Duffy map of the triangle). Vertices run counter-clockwise seen from the reflecting
side; the normal follows the right-hand rule.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable, Sequence
from typing import Any, Literal

import numpy as np
import torch
from torch import Tensor

from .._checks import check_count
from ..errors import ShapeError
from .checks import check_facets
from .derived import DerivedCache
from .duplicates import resolve_duplicates
from .measures import facet_areas, facet_centroids, facet_diameters, facet_normals

__all__ = ["Scene", "area_average", "split_quads"]

def _as_tensor(x: Any, name: str, dtype: torch.dtype | None = None) -> Tensor:
    if isinstance(x, Tensor):
        t = x
    else:
        try:
            t = torch.as_tensor(np.asarray(x))
        except Exception as exc:
            raise TypeError(f"{name} must be a tensor or array-like; got {type(x).__name__}") from exc
    if dtype is not None:
        t = t.to(dtype)
    elif not t.is_floating_point():
        t = t.to(torch.get_default_dtype())
    return t


class Scene:
    """A set of planar convex facets, each a triangle or a quad.

    Build one with :meth:`from_polygons`, :meth:`from_trimesh`, ``Scene(vertices, faces)`` or a builder in
    :mod:`torch_interreflect.scenes`.

    Args:
        vertices: Vertex positions in metres. Shape ``[V, 3]``.
        faces: Vertex indices of each facet, counter-clockwise seen from the reflecting side. Shape
            ``[F, 3]`` (triangles) or ``[F, 4]`` (planar convex quads).
        material: Optional material index of each facet. Shape ``[F]``.
        material_names: Optional names of the materials, indexed by ``material``.
        duplicates: What to do with coincident or overlapping coplanar facets facing the same way (the same
            surface counted twice, which makes form-factor rows sum above 1): ``"error"`` (default) raises
            :class:`~torch_interreflect.errors.GeometryError` naming the pairs, ``"drop"`` keeps the first facet
            of each overlapping group (by index; ``num_facets`` shrinks), ``"keep"`` skips the check.
            Back-to-back facets (opposite normals) and facets touching along an edge are not duplicates.

    Shape:
        - corners: ``[F, 4, 3]`` (triangles repeat their last vertex)
        - areas: ``[F]``, normals: ``[F, 3]``, centroids: ``[F, 3]``

    Example:
        >>> import torch, torch_interreflect as ti
        >>> v = torch.tensor([[0., 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
        >>> scene = ti.Scene(v, torch.tensor([[0, 1, 2, 3]]))
        >>> scene.num_facets, float(scene.areas[0])
        (1, 1.0)
    """

    def __init__(
        self,
        vertices: Tensor | np.ndarray | Sequence,
        faces: Tensor | np.ndarray | Sequence,
        *,
        material: Tensor | np.ndarray | Sequence | None = None,
        material_names: Sequence[str] | None = None,
        duplicates: Literal["error", "drop", "keep"] = "error",
    ) -> None:
        v = _as_tensor(vertices, "vertices")
        f = torch.as_tensor(np.asarray(faces) if not isinstance(faces, Tensor) else faces)
        if v.ndim != 2 or v.shape[1] != 3:
            raise ShapeError(f"vertices must have shape [V, 3]; got {list(v.shape)}")
        if f.ndim != 2 or f.shape[1] not in (3, 4):
            raise ShapeError(f"faces must have shape [F, 3] or [F, 4]; got {list(f.shape)}")
        if f.is_floating_point():
            raise TypeError(f"faces must hold integer indices; got dtype {f.dtype}")
        f = f.long().to(v.device)
        if f.numel() and (int(f.min()) < 0 or int(f.max()) >= v.shape[0]):
            raise ShapeError(
                f"faces index vertices 0..{v.shape[0] - 1}; got indices in [{int(f.min())}, {int(f.max())}]"
            )
        corners = v[f]
        self._init_from_corners(corners, material, material_names, duplicates=duplicates)

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_polygons(
        cls,
        corners: Tensor | np.ndarray | Sequence,
        *,
        material: Tensor | np.ndarray | Sequence | None = None,
        material_names: Sequence[str] | None = None,
        duplicates: Literal["error", "drop", "keep"] = "error",
    ) -> Scene:
        """Build a scene where every polygon is one facet.

        Args:
            corners: Polygon corners in metres, counter-clockwise seen from the reflecting side. Shape
                ``[F, 3, 3]`` (triangles) or ``[F, 4, 3]`` (planar convex quads).
            material: Optional material index per facet, shape ``[F]``.
            material_names: Optional names of the materials.
            duplicates: Coincident / overlapping coplanar facets: ``"error"``, ``"drop"`` or ``"keep"`` (see
                :class:`Scene`).

        Raises:
            GeometryError: a facet is non-finite, degenerate, non-planar or non-convex, or (``duplicates="error"``)
                two facets overlap (the message names them).
            ShapeError: ``corners`` does not have shape ``[F, 3, 3]`` or ``[F, 4, 3]``.

        Example:
            >>> import torch, torch_interreflect as ti
            >>> tri = torch.tensor([[[0., 0, 0], [1, 0, 0], [0, 1, 0]]])
            >>> ti.Scene.from_polygons(tri).normals.abs().tolist()
            [[0.0, 0.0, 1.0]]
        """
        c = _as_tensor(corners, "corners")
        if c.ndim != 3 or c.shape[1] not in (3, 4) or c.shape[2] != 3:
            raise ShapeError(f"corners must have shape [F, 3, 3] or [F, 4, 3]; got {list(c.shape)}")
        self = cls.__new__(cls)
        self._init_from_corners(c, material, material_names, duplicates=duplicates)
        return self

    @classmethod
    def from_trimesh(
        cls,
        mesh: Any,
        *,
        dtype: torch.dtype | None = None,
        side: Literal["outside", "inside", "both"] = "outside",
        duplicates: Literal["error", "drop", "keep"] = "error",
    ) -> Scene:
        """Build a scene from a :class:`trimesh.Trimesh`, one facet per triangle.

        **Which side reflects.** A facet reflects (and receives light) on the side its normal points to. trimesh
        winds faces so that normals point *out* of a closed mesh (and out of the convex side of a bowl or cup cut
        from a sphere), so with the default ``side="outside"`` the outer surface reflects, as before this option
        existed: a bowl's concave inside then exchanges no light and its form factors are all zero (``form_factors``
        warns). Pass ``side="inside"`` for the interior of a room, a box, a cup or a bowl (every face is wound the
        other way), or ``side="both"`` for a thin shell that reflects on both sides (each triangle becomes two
        back-to-back facets: facets ``0..T-1`` face outside, ``T..2T-1`` inside, with the same materials).

        A per-facet material index is kept when the mesh has face colours (one material per distinct colour)
        or a :class:`trimesh.Scene` was concatenated from several meshes (``mesh.metadata['material']``).

        Args:
            mesh: A ``trimesh.Trimesh`` (or a ``trimesh.Scene``, which is concatenated).
            dtype: Floating dtype of the result (default: torch's default dtype).
            side: ``"outside"`` (default: trimesh's normals), ``"inside"`` (flipped) or ``"both"``.
            duplicates: Coincident / overlapping coplanar facets: ``"error"``, ``"drop"`` or ``"keep"`` (see
                :class:`Scene`).

        Example:
            >>> import trimesh, torch_interreflect as ti
            >>> ti.Scene.from_trimesh(trimesh.creation.box()).num_facets
            12
            >>> inside = ti.Scene.from_trimesh(trimesh.creation.box(), side="inside")
            >>> float(ti.form_factors(inside).row_sums().min()) > 0.999  # a closed room
            True
        """
        import trimesh

        if side not in ("outside", "inside", "both"):
            raise ValueError(f"side must be 'outside', 'inside' or 'both'; got {side!r}")
        material = None
        names: list[str] | None = None
        if isinstance(mesh, trimesh.Scene):
            geoms = list(mesh.dump())
            mats = np.concatenate([np.full(len(g.faces), k) for k, g in enumerate(geoms)])
            names = [str(g.metadata.get("name", f"mesh{k}")) for k, g in enumerate(geoms)]
            mesh = trimesh.util.concatenate(geoms)
            material = mats
        if not isinstance(mesh, trimesh.Trimesh):
            raise TypeError(f"from_trimesh expects a trimesh.Trimesh or trimesh.Scene; got {type(mesh).__name__}")
        if material is None and getattr(mesh.visual, "kind", None) == "face":
            colours = np.asarray(mesh.visual.face_colors)
            uniq, inverse = np.unique(colours, axis=0, return_inverse=True)
            if len(uniq) > 1:
                material = inverse.reshape(-1)
                names = ["#" + "".join(f"{int(c):02x}" for c in u[:3]) for u in uniq]
        v = torch.as_tensor(np.asarray(mesh.vertices), dtype=dtype or torch.get_default_dtype())
        f = torch.as_tensor(np.asarray(mesh.faces, dtype=np.int64))
        if side != "outside":
            flipped = f.flip(1)
            f = flipped if side == "inside" else torch.cat([f, flipped])
            if side == "both" and material is not None:
                material = np.concatenate([np.asarray(material), np.asarray(material)])
        return cls(v, f, material=material, material_names=names, duplicates=duplicates)

    def _init_from_corners(
        self,
        corners: Tensor,
        material: Tensor | np.ndarray | Sequence | None,
        material_names: Sequence[str] | None,
        validate: bool = True,
        duplicates: str = "error",
    ) -> None:
        if corners.shape[1] == 3:
            corners = torch.cat([corners, corners[:, 2:3]], dim=1)
            is_tri = torch.ones(corners.shape[0], dtype=torch.bool, device=corners.device)
        else:
            is_tri = torch.zeros(corners.shape[0], dtype=torch.bool, device=corners.device)
        self._corners = corners.contiguous()
        self._is_triangle = is_tri
        if material is not None:
            m = torch.as_tensor(np.asarray(material) if not isinstance(material, Tensor) else material)
            m = m.long().to(corners.device).reshape(-1)
            if m.shape[0] != corners.shape[0]:
                raise ShapeError(f"material must have one entry per facet ([{corners.shape[0]}]); got {list(m.shape)}")
            self._material: Tensor | None = m
        else:
            self._material = None
        self.material_names = list(material_names) if material_names is not None else None
        if validate:
            self._validate()
            self._drop_duplicates(duplicates)

    def _drop_duplicates(self, mode: str) -> None:
        """Apply ``duplicates=`` (see :class:`Scene`) to the validated facets."""
        cd = self._corners.detach().to("cpu", torch.float64)
        keep = resolve_duplicates(cd.numpy(), facet_normals(cd).numpy(), mode)
        if keep is not None:
            k = torch.as_tensor(keep, device=self._corners.device)
            self._corners, self._is_triangle = self._corners[k].contiguous(), self._is_triangle[k]
            self._material = self._material[k] if self._material is not None else None

    @classmethod
    def from_parts(
        cls, corners: Tensor, is_triangle: Tensor, material: Tensor | None, material_names: list[str] | None
    ) -> Scene:
        """A scene from the parts of valid scenes (a subset, a detached copy, children of a subdivision), without
        validating them again: planarity, convexity and duplicates are not checked.

        Args:
            corners: Facet corners in metres, a triangle repeating its last corner. Shape ``[F, 4, 3]``.
            is_triangle: Which facets are triangles. Shape ``[F]`` bool.
            material: Material index per facet ``[F]`` (int64), or ``None``.
            material_names: Names of the materials, or ``None``.

        Example:
            >>> import torch_interreflect as ti
            >>> box = ti.scenes.closed_box(divisions=1)
            >>> floor = ti.Scene.from_parts(box.corners[:1], box.is_triangle[:1], box.material[:1], box.material_names)
            >>> floor.num_facets
            1
        """
        self = cls.__new__(cls)
        self._corners = corners.contiguous()
        self._is_triangle = is_triangle
        self._material = material
        self.material_names = material_names
        return self

    def _validate(self) -> None:
        check_facets(self._corners, self._is_triangle)

    # ------------------------------------------------------------------ properties
    @property
    def corners(self) -> Tensor:
        """Facet corners ``[F, 4, 3]`` in metres (triangles repeat their last corner)."""
        return self._corners

    @property
    def is_triangle(self) -> Tensor:
        """Boolean mask ``[F]``: which facets are triangles."""
        return self._is_triangle

    @property
    def material(self) -> Tensor | None:
        """Per-facet material index ``[F]``, or ``None``."""
        return self._material

    @property
    def num_facets(self) -> int:
        """Number of facets ``F``."""
        return int(self._corners.shape[0])

    @property
    def dtype(self) -> torch.dtype:
        return self._corners.dtype

    @property
    def device(self) -> torch.device:
        return self._corners.device

    def derived(self, key: Hashable, make: Callable[[], Any]) -> Any:
        """``make()``, computed once while the corners are unchanged (:mod:`.derived`; never where they require
        grad; shared: read-only): the areas, normals, centroids and diameters below, :meth:`.raycast.RayCaster.of`."""
        cache = self.__dict__.get("_derived")
        if cache is None:
            cache = self.__dict__["_derived"] = DerivedCache()
        return cache.get(self._corners, key, make)

    def clear_derived(self) -> None:
        """Forget the kept values: after writing the corners past their version counter (``.data``, numpy)."""
        self.__dict__.pop("_derived", None)

    def __getstate__(self) -> dict[str, Any]:  # the kept values (a ray caster does not pickle) are made again
        return {k: v for k, v in self.__dict__.items() if k != "_derived"}

    @property
    def areas(self) -> Tensor:
        """Facet areas ``[F]`` in m²."""
        return self.derived("areas", lambda: facet_areas(self._corners))

    @property
    def normals(self) -> Tensor:
        """Unit normals ``[F, 3]`` of the reflecting side."""
        return self.derived("normals", lambda: facet_normals(self._corners))

    @property
    def centroids(self) -> Tensor:
        """Area centroids ``[F, 3]`` in metres."""
        return self.derived("centroids", lambda: facet_centroids(self._corners))

    @property
    def diameters(self) -> Tensor:
        """Largest distance between two corners of each facet ``[F]`` in metres."""
        return self.derived("diameters", lambda: facet_diameters(self._corners))

    def to(self, *args: Any, **kwargs: Any) -> Scene:
        """Move/cast the corners like :meth:`torch.Tensor.to` (integer tensors keep their dtype); the scene itself
        when nothing changes (as a tensor's ``to``), with what it has cached."""
        c = self._corners.to(*args, **kwargs)
        if c is self._corners:
            return self
        dev = c.device
        mat = self._material.to(dev) if self._material is not None else None
        return Scene.from_parts(c, self._is_triangle.to(dev), mat, self.material_names)

    def detach(self) -> Scene:
        """The same facets with corners detached from autograd (ray casting, caches); the scene itself (the same
        corners tensor) when they do not require grad."""
        if not self._corners.requires_grad:
            return self
        return Scene.from_parts(self._corners.detach(), self._is_triangle, self._material, self.material_names)

    def __len__(self) -> int:
        return self.num_facets

    def __repr__(self) -> str:
        nt = int(self._is_triangle.sum())
        return (f"Scene(num_facets={self.num_facets}, quads={self.num_facets - nt}, triangles={nt}, "
                f"dtype={self.dtype}, device={self.device})")

    # ------------------------------------------------------------------ operations
    def subdivide(self, k: int) -> tuple[Scene, Tensor]:
        """Split each quad into ``k × k`` quads and each triangle into ``k²`` triangles.

        Args:
            k: Subdivision factor (``k >= 1``).

        Returns:
            ``(finer_scene, parent)``: ``parent[j]`` is the index of the facet that child ``j`` came from.
            Children of one facet are contiguous and their areas sum to the parent's.

        Shape:
            - parent: ``[F * k²]``

        Example:
            >>> import torch_interreflect as ti
            >>> fine, parent = ti.scenes.v_groove(45.0, divisions=2).subdivide(3)
            >>> fine.num_facets, int(parent.max())
            (72, 7)
        """
        k = int(check_count(k, "k", note=" (subdivide(k): facets per edge)"))
        c = self._corners
        dev, dt = c.device, c.dtype
        F = c.shape[0]
        if k == 1:
            return self, torch.arange(F, device=dev)
        quad_idx = torch.nonzero(~self._is_triangle).reshape(-1)
        tri_idx = torch.nonzero(self._is_triangle).reshape(-1)
        out_corners = torch.empty(F, k * k, 4, 3, device=dev, dtype=dt)
        out_tri = torch.zeros(F, k * k, dtype=torch.bool, device=dev)
        if quad_idx.numel():
            out_corners[quad_idx] = split_quads(c[quad_idx], k, k)
        if tri_idx.numel():
            t = c[tri_idx, :3]  # [T, 3, 3]
            a, b, cc = t.unbind(1)
            tris = []
            for i in range(k):
                for j in range(k - i):
                    p = lambda ii, jj: a + (b - a) * (ii / k) + (cc - a) * (jj / k)  # noqa: E731
                    tris.append(torch.stack([p(i, j), p(i + 1, j), p(i, j + 1), p(i, j + 1)], dim=1))
                    if j < k - i - 1:
                        tris.append(
                            torch.stack([p(i + 1, j), p(i + 1, j + 1), p(i, j + 1), p(i, j + 1)], dim=1)
                        )
            out_corners[tri_idx] = torch.stack(tris, dim=1)
            out_tri[tri_idx] = True
        parent = torch.arange(F, device=dev).repeat_interleave(k * k)
        mat = self._material.repeat_interleave(k * k) if self._material is not None else None
        fine = Scene.from_parts(out_corners.reshape(-1, 4, 3), out_tri.reshape(-1), mat, self.material_names)
        return fine, parent

    def average_to_parent(self, values: Tensor, parent: Tensor, fine: Scene) -> Tensor:
        """Area-average per-facet ``values`` of ``fine`` (from :meth:`subdivide`) back onto this scene.

        Args:
            values: Per-facet values of the finer scene, facets on dim ``-2``. Shape ``[..., F_fine, C]``.
            parent: The parent index returned by :meth:`subdivide`. Shape ``[F_fine]``.
            fine: The finer scene.

        Returns:
            Area-weighted means. Shape ``[..., F, C]``.
        """
        if values.shape[-2] != fine.num_facets or parent.shape[0] != fine.num_facets:
            raise ShapeError(
                f"values must have {fine.num_facets} facets on dim -2 and parent {fine.num_facets} entries; "
                f"got values {list(values.shape)}, parent {list(parent.shape)}"
            )
        return area_average(values, parent, fine.areas, self.num_facets)

    @staticmethod
    def concatenate(scenes: Sequence[Scene]) -> Scene:
        """Join several scenes into one; material indices are offset so each scene keeps its own."""
        if not scenes:
            raise ValueError("concatenate needs at least one scene; got none")
        corners = torch.cat([s.corners for s in scenes])
        tri = torch.cat([s.is_triangle for s in scenes])
        mats, names, off = [], [], 0
        for k, s in enumerate(scenes):
            if s.material is not None:
                mats.append(s.material + off)
                nm = s.material_names or [f"scene{k}_m{i}" for i in range(int(s.material.max()) + 1)]
                off += len(nm)
                names += nm
            else:
                mats.append(torch.full((s.num_facets,), off, dtype=torch.long, device=s.device))
                names.append(f"scene{k}")
                off += 1
        return Scene.from_parts(corners, tri, torch.cat(mats), names)

    def to_trimesh(self) -> Any:
        """The facets as a triangle :class:`trimesh.Trimesh` (quads split in two) and the facet of each face.

        Returns:
            ``(mesh, face_facet)`` where ``face_facet[t]`` is the facet that triangle ``t`` belongs to.
        """
        import trimesh

        c = self._corners.detach().double().cpu().numpy()
        F = c.shape[0]
        tri_mask = self._is_triangle.cpu().numpy()
        t1 = c[:, [0, 1, 2]]
        t2 = c[~tri_mask][:, [0, 2, 3]]
        tris = np.concatenate([t1, t2])
        owner = np.concatenate([np.arange(F), np.nonzero(~tri_mask)[0]])
        verts = tris.reshape(-1, 3)
        faces = np.arange(len(verts)).reshape(-1, 3)
        mesh = trimesh.Trimesh(verts, faces, process=False)
        return mesh, owner


def split_quads(corners: Tensor, ku: int, kv: int) -> Tensor:
    """Quads split ``ku × kv`` along their edges ``0→1`` and ``0→3`` (bilinear; children ``iu·kv + iv``, corners in
    order). Differentiable.

    Shape:
        - corners: ``[Q, 4, 3]``; output: ``[Q, ku·kv, 4, 3]``
    """
    su = torch.linspace(0, 1, ku + 1, dtype=corners.dtype, device=corners.device)[None, :, None, None]
    sv = torch.linspace(0, 1, kv + 1, dtype=corners.dtype, device=corners.device)[None, None, :, None]
    a, b, cc, d = (x[:, None, None, :] for x in corners.unbind(1))
    grid = (1 - su) * (1 - sv) * a + su * (1 - sv) * b + su * sv * cc + (1 - su) * sv * d  # [Q, ku+1, kv+1, 3]
    sub = torch.stack([grid[:, :-1, :-1], grid[:, 1:, :-1], grid[:, 1:, 1:], grid[:, :-1, 1:]], dim=3)
    return sub.reshape(corners.shape[0], ku * kv, 4, 3)


def area_average(values: Tensor, index: Tensor, weights: Tensor, size: int) -> Tensor:
    """Weighted means of ``values`` grouped by ``index``: ``out[..., k, :] = Σ_{index_j = k} w_j v_j / Σ w_j``.

    The tensor form of :meth:`Scene.average_to_parent` (pieces → the facets they came from); differentiable in
    ``values``.

    Args:
        values: Per-piece values, pieces on dim ``-2``. Shape ``[..., N, C]``.
        index: Group of each piece, in ``[0, size)``. Shape ``[N]``.
        weights: Weight of each piece (areas, m²). Shape ``[N]``.
        size: Number of groups.

    Returns:
        Shape ``[..., size, C]``.
    """
    w = weights.to(device=values.device, dtype=values.dtype)
    num = values.new_zeros(*values.shape[:-2], size, values.shape[-1]).index_add(-2, index, values * w[:, None])
    den = w.new_zeros(size).index_add(0, index, w)
    return num / den[:, None]
