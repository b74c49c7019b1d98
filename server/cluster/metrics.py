"""/metrics over the cluster: the owners' histograms and counters summed (the single-process names),
quantiles read off the summed histograms, and per-owner gauges labelled by node and owner."""

from __future__ import annotations

from ..metrics import SECONDS_BUCKETS, Histogram, Metrics, _labels, _num

QUANTILES = (0.5, 0.95)


def merged(parts: list[tuple[list[int], float]]) -> Histogram:
    """One histogram holding the observations of ``parts`` ((bucket counts, sum) on `SECONDS_BUCKETS`)."""
    out = Histogram()
    for counts, total in parts:
        out.counts = [a + b for a, b in zip(out.counts, counts)]
        out.sum += total
    return out


def quantile(hist: Histogram, q: float) -> float:
    """The ``q`` quantile of a histogram, linear within its bucket (as Prometheus' histogram_quantile);
    0 without observations; the last finite bound when it falls in the +Inf bucket."""
    n = sum(hist.counts)
    if n == 0:
        return 0.0
    rank, seen = q * n, 0
    for i, count in enumerate(hist.counts):
        if count and seen + count >= rank:
            if i == len(hist.buckets):
                return hist.buckets[-1]
            lower = hist.buckets[i - 1] if i else 0.0
            return lower + (hist.buckets[i] - lower) * (rank - seen) / count
        seen += count
    return hist.buckets[-1]


def exposition(reports: list[dict], sessions_on_disk: int, unreachable: int) -> str:
    """The cluster's /metrics text from the owners' `SessionOwner.report` dicts."""
    metrics = Metrics()
    metrics.fold_seconds = merged([r["fold"] for r in reports])
    for kind in sorted({k for r in reports for k in r["view"]}):
        metrics.view_seconds[kind] = merged([r["view"][kind] for r in reports if kind in r["view"]])
    metrics.frames_total = sum(r["frames_total"] for r in reports)
    metrics.storage_errors = sum(r["storage_errors"] for r in reports)
    for r in reports:
        for status, n in r["responses"].items():
            metrics.responses[int(status)] += n
    total = lambda key: sum(r[key] for r in reports)  # noqa: E731
    gauges = {
        "canonical_sessions": ("Sessions stored (held in memory or evicted to disk).", sessions_on_disk),
        "canonical_voxels": ("Voxels over the sessions held in memory.", total("voxels")),
        "canonical_frames": ("Frames folded over the sessions held in memory.", total("frames")),
        "canonical_jobs_active": ("Compute jobs running or waiting, over all owners.", total("jobs_active")),
        "canonical_jobs_limit": ("The queue limits, summed over owners.", total("jobs_limit")),
        "canonical_colour_solves_running": ("Background colour solves running now, over all owners.",
                                            total("solves_running")),
        "canonical_colour_solves_done_total": ("Background colour solves finished since the owners started.",
                                               total("solves_done")),
        "canonical_viewer_superseded_total": ("Viewer pictures replaced by a newer one while they waited, since "
                                              "the owners started.", total("superseded")),
        "canonical_sessions_unavailable": ("Sessions not served: their files need an operator (canonical repair).",
                                           total("unavailable")),
        "canonical_sessions_read_only": ("Sessions whose log cannot take frames until a restart.", total("wedged")),
        "canonical_snapshot_failures": ("Snapshots that failed (frames stay in the log).", total("snapshot_failures")),
        "canonical_storage_errors_total": ("Requests refused because storage could not make them durable.", metrics.storage_errors),
        "canonical_cluster_owners_unreachable": ("Owners that did not answer this scrape (restarting or lost).", unreachable),
    }
    lines = [metrics.exposition(gauges).rstrip("\n")]
    restore = merged([r["restore"] for r in reports])
    lines += _summary("canonical_fold_seconds_quantile", "Fold latency quantiles over all owners.", {"": metrics.fold_seconds})
    lines += _summary("canonical_view_seconds_quantile", "View latency quantiles over all owners, by kind.",
                      {k: h for k, h in sorted(metrics.view_seconds.items())}, "kind")
    lines += _summary("canonical_restore_seconds_quantile", "Session restore latency quantiles over all owners.", {"": restore})
    per_owner = (("canonical_cluster_sessions", "Sessions held in memory, by node and owner.", "sessions"),
                 ("canonical_cluster_memory_bytes", "Scene memory held, by node and owner.", "memory_bytes"),
                 ("canonical_cluster_folds_per_second", "Folds per second since the previous scrape, by node and owner.",
                  "folds_per_second"),
                 ("canonical_cluster_restores_total", "Sessions restored from disk, by node and owner.", "restores"),
                 ("canonical_cluster_evictions_total", "Idle sessions evicted from memory, by node and owner.", "evictions"))
    for name, help_text, key in per_owner:
        kind = "counter" if name.endswith("_total") else "gauge"
        lines += [f"# HELP {name} {help_text}", f"# TYPE {name} {kind}"]
        lines += [f"{name}{_labels({'node': r['node'], 'owner': str(r['owner'])})} {_num(r[key])}" for r in reports]
    return "\n".join(lines) + "\n"


def _summary(name: str, help_text: str, hists: dict[str, Histogram], label: str = "") -> list[str]:
    lines = [f"# HELP {name} {help_text}", f"# TYPE {name} gauge"]
    for value, hist in hists.items():
        for q in QUANTILES:
            labels = {"quantile": _num(q), **({label: value} if label else {})}
            lines.append(f"{name}{_labels(labels)} {_num(quantile(hist, q))}")
    return lines


__all__ = ["SECONDS_BUCKETS", "exposition", "merged", "quantile"]
