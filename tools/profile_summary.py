"""Seconds per function from a py-spy profile of a facecap run.

    pip install py-spy
    py-spy record -r 20 -f raw --subprocesses -o OUT/profile.raw -- \\
        python benchmarks/bench_pipeline.py ...
    python tools/profile_summary.py OUT/profile.raw --rate 20 [--match facecap_core/] [--top 40]

py-spy's ``raw`` output holds one line per distinct stack, ``frame;frame;... samples``. A
function's inclusive seconds are the samples whose stack holds it (once per stack), over the
rate; its own seconds those where it is the innermost frame. Samples are taken per thread,
so two busy threads count twice (seconds of CPU, not of wall clock). Numba kernels and
native code (COLMAP, OpenCV) show as the Python function that called them; py-spy leaves
out threads that wait with the GIL released unless given ``--idle``.
"""

from __future__ import annotations

import argparse
import re
from collections import Counter
from pathlib import Path

LINE_NUMBER = re.compile(r":\d+\)$")


def summarise(path: Path) -> tuple[Counter, Counter, int]:
    """(inclusive samples, own samples, total samples) per ``function (file)``."""
    inclusive, own, total = Counter(), Counter(), 0
    for line in path.read_text(errors="replace").splitlines():
        stack, _, count = line.rpartition(" ")
        if not count.isdigit():  # the continuation of a process title with a newline
            continue
        n = int(count)
        total += n
        frames = [LINE_NUMBER.sub(")", f) for f in stack.split(";")]
        for frame in set(frames):
            inclusive[frame] += n
        own[frames[-1]] += n
    return inclusive, own, total


def main() -> Path:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("profile", type=Path, help="py-spy record -f raw output")
    ap.add_argument("--rate", type=float, default=100.0, help="py-spy's sampling rate (-r)")
    ap.add_argument("--match", default="", help="only frames whose text holds this")
    ap.add_argument("--top", type=int, default=40)
    args = ap.parse_args()
    inclusive, own, total = summarise(args.profile)
    print(f"{total / args.rate:.1f} s sampled (all threads)")
    print("| inclusive s | own s | function (file) |\n|---:|---:|---|")
    shown = 0
    for frame, n in inclusive.most_common():
        if args.match in frame and not frame.startswith("process "):
            print(f"| {n / args.rate:.1f} | {own[frame] / args.rate:.1f} | `{frame}` |")
            shown += 1
            if shown == args.top:
                break
    return args.profile


if __name__ == "__main__":
    main()
