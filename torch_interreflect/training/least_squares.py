"""Levenberg–Marquardt for a scale-free least-squares fit with quadratic priors.

Minimises ``f(θ) = min_s ‖s p(θ) − o‖² + Σ_i w_i (θ_i − c_i)²`` over the ``free`` entries of ``θ``: the model's
overall scale ``s`` is projected out in closed form (variable projection, with Kaufman's Jacobian
``s (I − u uᵀ) J``, ``u = p / ‖p‖``, exact for the gradient since the residual is orthogonal to ``u``), the priors
enter the normal equations as ``W = diag(w)``, and each step solves ``(Jᵀ J + W + ν diag(Jᵀ J + W)) δ = −∇f / 2``.
A step is taken only when it lowers ``f``; ``ν`` is divided by 3 after a taken step and doubled after a refused one,
at most :data:`MAX_REFUSALS` times in a row (then the fit stops where it is).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["MAX_REFUSALS", "LMResult", "best_scale", "scaled_least_squares"]

#: Refused steps in a row (``ν`` doubled each time, 1024× in all) after which the fit stops.
MAX_REFUSALS = 10


@dataclass
class LMResult:
    """Result of :func:`scaled_least_squares`.

    Attributes:
        theta: The parameters reached ``[P]``.
        loss: ``f`` there (misfit after the best scale, plus the priors).
        misfit: ``min_s ‖s p − o‖²`` there.
        evaluations: Model evaluations (with or without the Jacobian).
        steps: Steps taken.
    """

    theta: Tensor
    loss: float
    misfit: float
    evaluations: int
    steps: int


def best_scale(p: Tensor, o: Tensor) -> Tensor:
    """``argmin_s ‖s p − o‖²`` (0 for a zero ``p``).

    Args:
        p: The model. Shape ``[N]``.
        o: The observation. Shape ``[N]``.

    Returns:
        ``s``, a 0-d tensor.
    """
    return (p @ o) / (p @ p).clamp_min(1e-300)


def scaled_least_squares(
    model: Callable[[Tensor], Tensor],
    model_jacobian: Callable[[Tensor, Tensor], tuple[Tensor, Tensor]],
    observed: Tensor,
    theta: Tensor,
    weights: Tensor,
    centre: Tensor,
    free: Tensor,
    *,
    max_steps: int,
    rtol: float,
    damping: float = 1e-3,
) -> LMResult:
    """Fit ``θ`` (its ``free`` entries) by Levenberg–Marquardt (module docstring).

    Args:
        model: ``θ [P] → p [N]``.
        model_jacobian: ``(θ, free) → (p [N], ∂p/∂θ_free [N, len(free)])``.
        observed: ``o [N]``.
        theta: Start ``[P]``.
        weights: Prior weights ``w ≥ 0`` ``[P]``.
        centre: Prior centres ``c`` ``[P]``.
        free: Indices of the entries to fit (int64).
        max_steps: Most Jacobian evaluations.
        rtol: Stop when a step lowers ``f`` by less than ``rtol · f``.
        damping: Starting ``ν``.

    Returns:
        An :class:`LMResult`.

    Shape:
        - observed: ``[N]``; theta, weights, centre: ``[P]``; free: ``[Q]``; the Jacobian ``[N, Q]``
    """

    def loss(th: Tensor, p: Tensor) -> tuple[float, float]:
        s = best_scale(p, observed)
        mis = float((s * p - observed).pow(2).sum())
        return mis + float((weights * (th - centre).pow(2)).sum()), mis

    f, mis = loss(theta, model(theta))
    evaluations, steps, nu = 1, 0, damping
    w = weights[free]
    for _ in range(max_steps):
        p, jac = model_jacobian(theta, free)
        evaluations += 1
        s = best_scale(p, observed)
        res = s * p - observed
        u = p / p.norm().clamp_min(1e-300)
        jr = s * (jac - u[:, None] * (u @ jac))  # the residual's Jacobian with s projected out
        a = jr.T @ jr + torch.diag(w)
        grad = jr.T @ res + w * (theta[free] - centre[free])
        if not bool(grad.any()):  # a stationary point (e.g. a zero image): no step can lower f
            break
        diag = a.diagonal().clamp_min(1e-30)
        taken = False
        for _ in range(MAX_REFUSALS):
            step = torch.linalg.solve(a + nu * torch.diag(diag), -grad)
            trial = theta.clone()
            trial[free] += step
            f_new, mis_new = loss(trial, model(trial))
            evaluations += 1
            if f_new < f:
                taken, decrease = True, (f - f_new) / max(f, 1e-300)
                theta, f, mis, nu = trial, f_new, mis_new, max(nu / 3, 1e-12)
                steps += 1
                break
            nu *= 2
        if not taken or decrease < rtol:
            break
    return LMResult(theta, f, mis, evaluations, steps)
