"""Re-exports of moved public names that warn once (``DeprecationWarning`` naming the new home)."""

from __future__ import annotations

import functools
import importlib
import warnings
from collections.abc import Callable
from typing import Any, TypeVar

__all__ = ["moved_attribute", "renamed_keywords", "warn_once"]

F = TypeVar("F", bound=Callable[..., Any])

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
    warn_once(key, f"{key} moved to {new_module}.{new_name}; the old name will be removed in the next release",
              stacklevel=4)
    return getattr(importlib.import_module(new_module), new_name)


def warn_once(key: str, message: str, *, stacklevel: int = 3) -> None:
    """A ``DeprecationWarning`` with ``message``, the first time ``key`` is seen in this process.

    ``stacklevel`` counts from the caller of ``warn_once`` plus one (the default points at its caller's caller).
    """
    if key in _WARNED:
        return
    _WARNED.add(key)
    warnings.warn(message, DeprecationWarning, stacklevel=stacklevel)


def renamed_keywords(**renames: str) -> Callable[[F], F]:
    """Decorator: accept old keyword names for one release, with a ``DeprecationWarning`` naming the new one.

    ``@renamed_keywords(tol="quadrature_tol")`` maps a call ``f(..., tol=x)`` to ``f(..., quadrature_tol=x)``;
    passing both names raises ``TypeError``.
    """

    def wrap(func: F) -> F:
        @functools.wraps(func)
        def inner(*args: Any, **kwargs: Any) -> Any:
            for old, new in renames.items():
                if old not in kwargs:
                    continue
                if new in kwargs:
                    raise TypeError(f"{func.__qualname__}() got both {old!r} (old name) and {new!r}; pass only {new!r}")
                warnings.warn(
                    f"{func.__qualname__}({old}=...) is now {func.__qualname__}({new}=...); the old keyword "
                    "will be removed in the next release",
                    DeprecationWarning,
                    stacklevel=2,
                )
                kwargs[new] = kwargs.pop(old)
            return func(*args, **kwargs)

        return inner  # type: ignore[return-value]

    return wrap
