"""The geometry stage: scenes as tensors of planar facets, built-in scene builders, ray casting.

- :mod:`.scene`: :class:`Scene` (facets as tensors, subdivision, area averaging) and :func:`area_average`.
- :mod:`.scenes`: builders (``v_groove``, ``box_corner``, ``closed_box``, ``w_shape``, ``cornell_box``, ``room``).
- :mod:`.raycast`: :class:`RayCaster` (Embree, through ``embreex``; imported on first use).
- :mod:`.contacts`: :func:`split_at_contacts` (split facets where another facet stands on them).
- :mod:`.sizing`: :func:`subdivide_to` (split every facet into pieces no longer than a length).
- :mod:`.openings`: :func:`~.openings.openings` (the convex hull's faces that no facet covers: where a sky shines in).
- :mod:`.gaps`: :func:`~.gaps.near_pairs` (facets that nearly touch: a wall hung a few centimetres over a floor).
"""

from . import scenes
from .contacts import contact_pairs, split_at_contacts
from .raycast import RayCaster
from .scene import Scene, area_average
from .sizing import subdivide_to

__all__ = ["RayCaster", "Scene", "area_average", "contact_pairs", "scenes", "split_at_contacts", "subdivide_to"]
