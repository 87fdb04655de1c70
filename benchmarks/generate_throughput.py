"""Throughput of ``interreflect generate`` as a user runs it: the command before the fused kernel against now.

Each cell is one fresh ``interreflect generate --size 64x64`` process (default options otherwise), timed from the
outside (what the user waits: start-up, imports and compiled-kernel loading included) and by the command itself
(``generate``'s own seconds: from the first sample on). Configurations:

- *torch, 1 process*: today's code with the compiled kernels off (``TI_DISABLE_NUMBA=1``: the torch quadrature)
  and ``--workers 1``: the command before the fused kernel and ``--workers``, less the later changes that do not
  depend on them (e.g. the 0.26 s import of sympy that ``torch.broadcast_shapes`` made), so the speed-ups against it
  are approximate;
- *fused, 1 process*: the compiled kernels, ``--workers 1``;
- *fused, auto*: the default (``--workers auto``: one process per 32 samples to render, up to the cores).

at ``--count 8`` (start-up dominates) and ``--count 500`` (the README's example and ``train-cc``'s default data
set). Bytes: the hash of every file written by the fused runs must not depend on the number of processes; the torch
and fused images are compared.

Usage: ``python -m benchmarks.generate_throughput [--count N]`` → ``benchmarks/results/generate_throughput.md``
(~6 min on 2 cores).
"""

from __future__ import annotations

import argparse
import hashlib
import os
import platform
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks._common import HERE

CONFIGS = {"torch, 1 process": ("1", "1"), "fused, 1 process": ("0", "1"), "fused, auto": ("0", "auto")}


def run(disable_numba: str, workers: str, count: int) -> dict:
    """One ``interreflect generate`` process: wall seconds, the command's own seconds and processes, file hash,
    images."""
    env = {**os.environ, "TI_DISABLE_NUMBA": disable_numba}
    exe = Path(sys.executable).with_name("interreflect")
    with tempfile.TemporaryDirectory() as out:
        t = time.perf_counter()
        res = subprocess.run([str(exe), "generate", "--out", out, "--count", str(count), "--size", "64x64",
                              "--workers", workers, "--no-progress"], check=True, env=env, capture_output=True,
                             text=True)
        wall = time.perf_counter() - t
        m = re.search(r"in ([0-9.]+) s( on (\d+) processes)?", res.stdout)
        h = hashlib.sha1()
        images = {}
        for f in sorted(Path(out).rglob("*")):
            if f.is_file():
                h.update(f.relative_to(out).as_posix().encode())
                h.update(f.read_bytes())
                if f.suffix == ".npy" and not f.name.startswith("_"):
                    images[f.relative_to(out).as_posix()] = np.load(f)
    return {"wall": wall, "own": float(m.group(1)), "procs": int(m.group(3) or 1), "hash": h.hexdigest()[:12],
            "images": images}


def largest_difference(a: dict, b: dict) -> float:
    """Largest ``|a − b| / max |a|`` over the images both runs wrote (inf when the file lists differ)."""
    if a.keys() != b.keys():
        return float("inf")
    return max((float(np.abs(a[k].astype(np.float64) - b[k]).max() / max(np.abs(a[k]).max(), 1e-30)) for k in a),
               default=0.0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=500,
                    help="the large count (default 500, as the README's example and train-cc)")
    ap.add_argument("--out", default=str(HERE / "results" / "generate_throughput.md"))
    args = ap.parse_args()
    results = {}
    for count in (8, args.count):
        for name, (dis, w) in CONFIGS.items():
            results[(name, count)] = r = run(dis, w, count)
            print(name, count, {k: v for k, v in r.items() if k != "images"}, flush=True)
    load = os.getloadavg()
    lines = [
        "# `interreflect generate` at 64 × 64: samples per second, before and now",
        "",
        f"`python -m benchmarks.generate_throughput`, one run; {os.cpu_count()} cores, Python "
        f"{platform.python_version()}; load average at the end {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f}. "
        "Each cell is one fresh process with the default options; *wall*: timed from outside (start-up included), "
        "*own*: the seconds the command reports (from its first sample on). Speed-ups against *torch, 1 process* "
        "(today's code with the compiled kernels off, `TI_DISABLE_NUMBA=1`, and `--workers 1`: the command before "
        "the fused kernel and `--workers`, less later changes that do not depend on them) at the same count.",
        "",
        "| count | configuration | processes | wall s | samples/s (wall) | own s | samples/s (own) | × before (wall) "
        "| × before (own) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for count in (8, args.count):
        base = results[("torch, 1 process", count)]
        for name in CONFIGS:
            r = results[(name, count)]
            lines.append(f"| {count} | {name} | {r['procs']} | {r['wall']:.1f} | {count / r['wall']:.2f} | "
                         f"{r['own']:.1f} | {count / r['own']:.2f} | {base['wall'] / r['wall']:.2f}× | "
                         f"{base['own'] / r['own']:.2f}× |")
    same = all(results[("fused, 1 process", c)]["hash"] == results[("fused, auto", c)]["hash"]
               for c in (8, args.count))
    diff = largest_difference(results[("torch, 1 process", args.count)]["images"],
                              results[("fused, 1 process", args.count)]["images"])
    lines += [
        "",
        f"Bytes: the fused runs wrote {'the same bytes' if same else 'DIFFERENT bytes'} in 1 process and with "
        f"`--workers auto` (hash of every file, both counts). Torch against fused images (count {args.count}): at "
        f"most {diff:.1e} of their maximum apart (the compiled visibility rounds its rays and weights differently; "
        "a ray that grazes a face can flip).",
    ]
    Path(args.out).write_text("\n".join(lines) + "\n")
    print(Path(args.out).read_text())


if __name__ == "__main__":
    main()
