"""The ``interreflect`` command (``demo``, ``generate``, ``train-cc``) and the demo it runs."""

from .main import main

__all__ = ["main"]
