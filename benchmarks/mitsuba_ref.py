"""The Mitsuba 3 reference: ``python -m benchmarks.mitsuba_ref check | noise | offset-bias | report | references``.

The code is :mod:`benchmarks._common.mitsuba` (shared with the other benchmarks); this module is its command.
"""

from benchmarks._common.mitsuba import main

if __name__ == "__main__":
    main()
