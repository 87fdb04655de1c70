"""Shared oracles for the tests: exact reference values and small systems with known structure.

Howell's catalogue of configuration factors (DESIGN.md §2) and reciprocal form-factor matrices built so that
``A_i F_ij = A_j F_ji`` holds exactly. One copy each; test modules import from here (``from tests.oracles
import ...``) or use the fixtures of ``conftest.py``.
"""

from __future__ import annotations

import torch

from torch_interreflect import FormFactors

F64 = torch.float64

#: Howell C-16: unit squares sharing an edge at an angle (degrees) → F. 6–7 significant digits.
HOWELL_C16 = [(30, 0.619028), (45, 0.483348), (60, 0.370905), (90, 0.2000438), (120, 0.086615), (150, 0.021345)]
#: Howell C-14: perpendicular unit squares sharing an edge (the 90° row of C-16), and l = 1, w = 1 → h = 2.
HOWELL_C14_SQUARES = 0.2000438
HOWELL_C14_L1_W1_H2 = 0.2328526
#: Howell C-11: directly opposed unit squares at a gap → F.
HOWELL_C11 = [(1.0, 0.1998249), (0.5, 0.4152533), (2.0, 0.0685896)]
#: A differential area under the centre of a unit square at height 1.
POINT_UNDER_SQUARE = 0.2394565


def reference_tolerance(ref: float, rel: float) -> float:
    """The larger of a relative accuracy and half a unit in the last digit the reference gives."""
    text = f"{ref:.7g}"
    digits = len(text.split(".")[1].rstrip("0")) if "." in text else 0
    return max(rel * ref, 0.5 * 10.0**-digits)


def random_reciprocal(n: int, scale: float = 0.9, dtype: torch.dtype = F64, seed: int = 0) -> FormFactors:
    """Random symmetric ``S``, ``F = S / A`` (reciprocal), scaled so that the largest row sum is ``scale``."""
    g = torch.Generator().manual_seed(seed)
    s = torch.rand(n, n, generator=g, dtype=F64)
    s = s + s.T
    s.fill_diagonal_(0)
    areas = torch.rand(n, generator=g, dtype=F64) + 0.5
    f = s / areas[:, None]
    f = f / f.sum(1).max() * scale
    return FormFactors(f.to(dtype), areas.to(dtype))


def per_column_solve(f: torch.Tensor, r: torch.Tensor, e0: torch.Tensor) -> torch.Tensor:
    """``E`` with ``(I − F R) E = E0`` for every column, by ``torch.linalg.solve`` on one matrix at a time.

    The reference the solver tests compare with, differentiable by autograd. One matrix per call on purpose:
    batched LU on torch 2.13 CPU gives invalid pivots (or silently wrong solutions) with 2 threads at ~200 rows.

    Shape:
        - f: ``[F, F]``; r, e0: ``[..., F, L]`` (broadcast); output: the broadcast shape
    """
    r, e0 = torch.broadcast_tensors(r, e0)
    eye = torch.eye(f.shape[0], dtype=f.dtype)
    cols_r = r.movedim(-2, -1).reshape(-1, f.shape[0])
    cols_e = e0.movedim(-2, -1).reshape(-1, f.shape[0])
    out = torch.stack([torch.linalg.solve(eye - f * rc, ec) for rc, ec in zip(cols_r, cols_e, strict=True)])
    return out.reshape(*r.shape[:-2], r.shape[-1], r.shape[-2]).movedim(-1, -2)


def polygon_pixel_areas(poly: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Exact area of a convex image-space polygon ``[K, 2]`` (pixel coordinates, column then row) inside each pixel
    ``[H, W]`` (pixel ``(v, u)`` covers ``[u − ½, u + ½] × [v − ½, v + ½]``): Sutherland–Hodgman clipping to each
    pixel square, then the shoelace formula. Float64, slow (a test oracle)."""
    pts = [tuple(float(x) for x in p) for p in poly.detach().double()]
    out = torch.zeros(height, width, dtype=F64)
    u0, v0 = min(p[0] for p in pts), min(p[1] for p in pts)
    u1, v1 = max(p[0] for p in pts), max(p[1] for p in pts)
    for v in range(max(0, int(v0 + 0.5) - 1), min(height, int(v1 + 0.5) + 2)):
        for u in range(max(0, int(u0 + 0.5) - 1), min(width, int(u1 + 0.5) + 2)):
            clipped = pts
            for axis, bound, keep_above in ((0, u - 0.5, True), (0, u + 0.5, False), (1, v - 0.5, True),
                                            (1, v + 0.5, False)):
                def inside(p, a=axis, b=bound, k=keep_above):
                    return p[a] >= b if k else p[a] <= b

                def cut(p, q, a=axis, b=bound):
                    t = (b - p[a]) / (q[a] - p[a])
                    return (p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1]))

                nxt = []
                for i, q in enumerate(clipped):
                    p = clipped[i - 1]
                    if inside(q):
                        if not inside(p):
                            nxt.append(cut(p, q))
                        nxt.append(q)
                    elif inside(p):
                        nxt.append(cut(p, q))
                clipped = nxt
                if not clipped:
                    break
            if len(clipped) >= 3:
                xs = [p[0] for p in clipped]
                ys = [p[1] for p in clipped]
                out[v, u] = 0.5 * abs(sum(xs[i - 1] * ys[i] - xs[i] * ys[i - 1] for i in range(len(xs))))
    return out
