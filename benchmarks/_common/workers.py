"""One measurement in a fresh process (so that its memory high-water mark and caches are its own)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Sequence

from . import ROOT

__all__ = ["run_worker"]


def run_worker(module: str, args: Sequence[str], *, timeout: float | None = None,
               env: dict[str, str] | None = None) -> dict:
    """Run ``python -m module *args`` from the repository root; return the JSON object of its last ``{`` line.

    Args:
        module: e.g. ``"benchmarks.formfactors"``.
        args: Its arguments.
        timeout: Seconds before it is stopped.
        env: Extra environment variables (``OMP_WAIT_POLICY=PASSIVE`` is always set).

    Returns:
        The worker's record, or ``{"error": …, "returncode": …}`` when it failed, printed nothing or timed out.
    """
    full_env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE", **(env or {})}
    try:
        p = subprocess.run([sys.executable, "-m", module, *args], capture_output=True, text=True, cwd=ROOT,
                           env=full_env, timeout=timeout, check=False)
    except subprocess.TimeoutExpired:
        return {"error": f"timed out after {timeout:.0f} s", "returncode": None}
    lines = [s for s in p.stdout.splitlines() if s.startswith("{")]
    if p.returncode != 0 or not lines:
        return {"error": (p.stderr.strip().splitlines() or ["no output"])[-1][:200], "returncode": p.returncode}
    return json.loads(lines[-1])
