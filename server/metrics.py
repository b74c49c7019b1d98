"""Prometheus metrics, written by hand in the text exposition format (version 0.0.4).

A handful of histograms and counters do not justify the prometheus_client dependency; this is the
whole of it. Values are updated on the event loop (after a job returns), so no locking is needed.
"""

from __future__ import annotations

import bisect
from collections import defaultdict

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"
SECONDS_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)


def _labels(labels: dict[str, str]) -> str:
    if not labels:
        return ""
    return "{" + ",".join(f'{k}="{v}"' for k, v in sorted(labels.items())) + "}"


def _num(x: float) -> str:
    x = float(x)
    return str(int(x)) if x.is_integer() and abs(x) < 1e15 else repr(x)


class Histogram:
    def __init__(self, buckets=SECONDS_BUCKETS):
        self.buckets = tuple(buckets)
        self.counts = [0] * (len(self.buckets) + 1)
        self.sum = 0.0

    def observe(self, value: float) -> None:
        self.counts[bisect.bisect_left(self.buckets, value)] += 1
        self.sum += value

    def lines(self, name: str, labels: dict[str, str]) -> list[str]:
        out, cumulative = [], 0
        for bound, count in zip((*self.buckets, float("inf")), self.counts):
            cumulative += count
            le = "+Inf" if bound == float("inf") else _num(bound)
            out.append(f"{name}_bucket{_labels({**labels, 'le': le})} {cumulative}")
        out.append(f"{name}_sum{_labels(labels)} {_num(self.sum)}")
        out.append(f"{name}_count{_labels(labels)} {cumulative}")
        return out


class Metrics:
    def __init__(self):
        self.fold_seconds = Histogram()
        self.view_seconds: dict[str, Histogram] = defaultdict(Histogram)  # by kind: render, features, ...
        self.frames_total = 0
        self.responses: dict[int, int] = defaultdict(int)
        self.storage_errors = 0  # requests refused because their data could not be made durable

    def exposition(self, gauges: dict[str, tuple[str, float]]) -> str:
        """The text format; ``gauges`` maps name -> (help, value) for values read at scrape time (those
        named ``*_total`` are counters: they only grow while the process lives)."""
        lines = ["# HELP canonical_fold_seconds Time to decode, log (fsync) and fold one frame.",
                 "# TYPE canonical_fold_seconds histogram", *self.fold_seconds.lines("canonical_fold_seconds", {}),
                 "# HELP canonical_view_seconds Time to decode (if not cached), render and encode one view.",
                 "# TYPE canonical_view_seconds histogram"]
        for kind, hist in sorted(self.view_seconds.items()):
            lines += hist.lines("canonical_view_seconds", {"kind": kind})
        lines += ["# HELP canonical_frames_folded_total Frames folded and acknowledged since start.",
                  "# TYPE canonical_frames_folded_total counter", f"canonical_frames_folded_total {self.frames_total}",
                  "# HELP canonical_http_responses_total HTTP responses by status code.",
                  "# TYPE canonical_http_responses_total counter"]
        lines += [f'canonical_http_responses_total{{status="{s}"}} {n}' for s, n in sorted(self.responses.items())]
        for name, (help_text, value) in gauges.items():
            kind = "counter" if name.endswith("_total") else "gauge"
            lines += [f"# HELP {name} {help_text}", f"# TYPE {name} {kind}", f"{name} {_num(value)}"]
        return "\n".join(lines) + "\n"
