"""Accuracy as an input: :func:`render` and :func:`plan` refine the mesh and choose every setting for a
requested relative error, and report the error they estimate they left."""

from .render import BUDGET, AccuracyReport, Plan, RenderResult, plan, render

__all__ = ["BUDGET", "AccuracyReport", "Plan", "RenderResult", "plan", "render"]
