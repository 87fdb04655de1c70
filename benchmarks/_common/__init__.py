"""What the benchmark scripts share (one copy each):

- :mod:`.mitsuba`: the Mitsuba 3 reference wiring (per-facet irradiance of a scene, closed-form checks, the
  cached references, pooling of renders);
- :mod:`.ours`: this library's side (``solve``/``render`` and the direct light of a reference's light);
- :mod:`.timing`: best-of-n wall times;
- :mod:`.memory`: resident-set readings from ``/proc`` (current, peak, peak since a reset, available);
- :mod:`.report`: error metrics and formats, the machine line, writing a result file;
- :mod:`.workers`: one measurement in a fresh process (its own memory high-water mark).
"""

from pathlib import Path

#: ``benchmarks/``.
HERE = Path(__file__).resolve().parents[1]
#: The repository root (the working folder of worker processes, so ``python -m benchmarks.…`` resolves).
ROOT = HERE.parent
#: Where results are written.
RESULTS = HERE / "results"
