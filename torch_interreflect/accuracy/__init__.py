"""Accuracy as an input: :func:`render` and :func:`plan` refine the mesh and choose every setting for a
requested relative error, and report the error they estimate they left."""

from .plan import Plan, plan
from .render import render
from .report import AccuracyReport, RenderResult
from .settings import BUDGET

__all__ = ["BUDGET", "AccuracyReport", "Plan", "RenderResult", "plan", "render"]
