"""Inverse tools with known geometry: recover reflectance or illuminant, remove interreflections, recolour.

Notation (DESIGN.md §1): ``E = E0 + F B`` with radiosity ``B = R E = π L``; camera RGB ``ρ = camera(L)``.

**Reflectance from spectral radiance (exact).** With ``B = π L`` observed on every facet, the irradiance is
``E = E0 + F B`` (one product), so ``R = B / (E0 + F B)`` per facet and wavelength (:func:`reflectance_from_radiance`).
No solve is needed.

**Reflectance from camera RGB (least squares).** With reflectance in a linear basis, ``r_f = m + c_f P``, the camera
response ``ρ_f = K (r_f ⊙ E_f)`` (``K = C Δλ / π``) is linear in ``c_f`` *for a given irradiance* ``E_f``. The
``"alternating"`` method solves the small per-facet least-squares problems for ``c`` with ``E`` fixed (starting from
``E = E0``, which is the estimate that ignores interreflection), then updates ``E = solve(F, R, E0)``, and repeats
to a fixed point; with ``bounces=1`` (interreflection not modelled) it stops after the first step. The
``"gradient"`` method minimises the relative squared RGB error through the differentiable renderer with L-BFGS
(any basis, e.g. the sigmoid one), starting from the alternating solution.

**Interreflection removal.** The one-bounce (direct-only) radiosity is ``B1 = R E0``. From ``E = E0 + F B`` and
``R = B / E``: ``B1 = R (E − F B) = B − R F B = B · E0 / (E0 + F B)``. This is the cancellation idea of Seitz et al.
(2005), ``B1 = (I − R F) B``, with the unknown reflectance eliminated by the known light, exact per wavelength
(:func:`remove_interreflections` with spectral radiance). From camera RGB the same formula applied per channel
(``E0`` replaced by its camera response) is exact only for narrow-band channels; the ``basis`` option instead
recovers reflectances in a basis (above) and renders ``R E0``, exact when the true reflectances lie in the basis.

**Illuminant estimation.** :func:`estimate_illuminant` fits an illuminant model (CIE daylight by ``M1, M2`` or by
CCT, or a blackbody) and a scale to observed RGB by L-BFGS through the renderer.

**Recolouring.** :func:`recolor` changes the reflectance of some facets and re-solves: the colour bleeding onto
every other facet follows. With an ``observed`` image, the *change* predicted by the model is added to it.
"""

from .illuminant import IlluminantEstimate, estimate_illuminant
from .recolor import Recolored, recolor
from .reflectance import ReflectanceEstimate, estimate_reflectance, reflectance_from_radiance
from .removal import remove_interreflections

__all__ = [
    "IlluminantEstimate",
    "Recolored",
    "ReflectanceEstimate",
    "estimate_illuminant",
    "estimate_reflectance",
    "recolor",
    "reflectance_from_radiance",
    "remove_interreflections",
]
