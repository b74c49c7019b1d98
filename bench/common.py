"""Shared pieces of the benchmarks: the machine header, a plain-text table printer, and the
evaluation's split of a capture."""

from __future__ import annotations

import os
import platform
import time

import numpy as np


def machine_summary() -> str:
    """One paragraph naming the machine, so every printed table says where it ran."""
    cpu = platform.processor() or "unknown CPU"
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    import numba
    import torch

    load = ""
    if hasattr(os, "getloadavg"):
        load = (f"load average {' / '.join(f'{x:.2f}' for x in os.getloadavg())} (1 / 5 / 15 min: other work on "
                "the machine skews timings)\n")
    return (f"machine: {platform.node()} | {cpu} | {os.cpu_count()} cores | {platform.system()} {platform.release()}\n"
            f"python {platform.python_version()} | torch {torch.__version__} ({torch.get_num_threads()} threads) | "
            f"numba {numba.__version__} ({numba.get_num_threads()} threads) | numpy {np.__version__}\n" + load)


def time_each(fn, items) -> list[float]:
    """Milliseconds of ``fn(item)`` for each item, in order."""
    ms = []
    for item in items:
        t0 = time.perf_counter()
        fn(item)
        ms.append((time.perf_counter() - t0) * 1000)
    return ms


def status_bytes(field: str) -> int:
    """A figure of /proc/self/status in bytes: ``VmRSS`` (resident now) or ``VmHWM`` (its peak)."""
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) * 1024 for line in f if line.startswith(field + ":"))


def process_mib(pid: int) -> dict[str, float]:
    """VmRSS, RssAnon and RssFile of process ``pid`` in MiB (empty once it is gone)."""
    try:
        lines = open(f"/proc/{pid}/status").read().splitlines()
    except OSError:
        return {}
    fields = dict(line.split(":", 1) for line in lines if ":" in line)
    return {k: int(fields[k].split()[0]) / 1024 for k in ("VmRSS", "RssAnon", "RssFile") if k in fields}


def peak_growth(fn, *args) -> tuple[float, int]:
    """(ms, bytes) of ``fn(*args)``: its time, and how far resident memory rose above where it
    started, at its peak (the peak is reset to the current figure first: /proc/self/clear_refs)."""
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")
    before = status_bytes("VmRSS")
    t0 = time.perf_counter()
    fn(*args)
    return (time.perf_counter() - t0) * 1000, status_bytes("VmHWM") - before


def stats_ms(values) -> str:
    v = np.asarray(values, dtype=np.float64)
    return f"{np.median(v):.2f} / {v.min():.2f} / {v.max():.2f}"


def print_table(title: str, rows: list[dict]) -> None:
    """Print ``rows`` (dicts with the same keys) as an aligned Markdown table under ``title``."""
    if not rows:
        return
    cols = list(rows[0])
    width = {c: max(len(c), *(len(str(r.get(c, ""))) for r in rows)) for c in cols}
    print(f"### {title}")
    print("| " + " | ".join(c.ljust(width[c]) for c in cols) + " |")
    print("|" + "|".join("-" * (width[c] + 2) for c in cols) + "|")
    for r in rows:
        print("| " + " | ".join(str(r.get(c, "")).ljust(width[c]) for c in cols) + " |")
    print()


def held_out_split(data, views: list[int]):
    """A capture (any `load_dataset` layout) under the evaluation's interpolation split for input
    counts ``views``: (its frames, the split, the held-out frames)."""
    from canonical_core.datasets import load_dataset
    from canonical_core.eval.protocol import interpolation_split

    frames = load_dataset(data)
    split = interpolation_split(len(frames), views)
    return frames, split, [frames[i] for i in split.heldout]
