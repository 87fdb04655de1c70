"""Re-exports of moved public names that warn once (``DeprecationWarning`` naming the new home)."""

from __future__ import annotations

import importlib
import warnings
from typing import Any

__all__ = ["moved_attribute"]

_WARNED: set[str] = set()


def moved_attribute(module: str, name: str, moved: dict[str, Any]) -> Any:
    """Return ``module.name`` from its new home, warning once per name; ``AttributeError`` for unknown names.

    Args:
        module: The old module's ``__name__``.
        name: The attribute asked for.
        moved: ``{old name: new module}`` or ``{old name: (new module, new name)}``.
    """
    if name not in moved:
        raise AttributeError(f"module {module!r} has no attribute {name!r}")
    target = moved[name]
    new_module, new_name = target if isinstance(target, tuple) else (target, name)
    key = f"{module}.{name}"
    if key not in _WARNED:
        _WARNED.add(key)
        warnings.warn(
            f"{key} moved to {new_module}.{new_name}; the old name will be removed in the next release",
            DeprecationWarning,
            stacklevel=3,
        )
    return getattr(importlib.import_module(new_module), new_name)
