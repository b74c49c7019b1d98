"""Snapshots and session files of earlier layouts: their top-level names moved into groups
(`FLAT_NAMES`), and `migrate_flat` brings such a mapping to the current layout (`SceneConfig.from_dict`
does). Plain mappings in and out: no settings model is needed to move names."""

from __future__ import annotations

# Top-level names of earlier layouts -> their path now. Snapshots and session files written with them
# still load.
FLAT_NAMES: dict[str, str] = {
    "depth_sigma0": "sensor.sigma0",
    "depth_sigma2": "sensor.sigma2",
    "depth_sigma_ref": "sensor.sigma_ref",
    "depth_edge_weight": "sensor.edge_weight",
    "free_space_margin": "free_space.margin",
    "free_space_sigmas": "free_space.sigmas",
    "free_space_cell": "free_space.cell",
    "free_space_history": "free_space.history",
    "free_space_dominance": "free_space.dominance",
    "depth_sources": "depth.sources",
    "depth_hypotheses": "depth.hypotheses",
    "source_window": "depth.source_window",
    "depth_completion_radius": "depth.completion_radius",
    "depth_denoise_radius": "depth.denoise_radius",
    "opacity_slope": "decoder.opacity_slope",
    "opacity_bias": "decoder.opacity_bias",
    "sh_regularization": "decoder.sh_regularization",
    "weighting": "research.weighting",
    "eps": "research.eps",
    "near": "range.near",
    "far": "range.far",
    "feature_backend": "features.backend",
    "feature_dim": "features.dim",
    "depth_completion": "depth.completion",
    "colour_solve_views": "colour_solve.views",
    "colour_solve_refresh": "colour_solve.refresh",
    "colour_solve_scale": "colour_solve.scale",
}

# Layouts before the sensor families wrote every noise value and no family; those values were the
# structured-light model's or set by hand, so such a group keeps them under that family's name.
EARLIER_SENSOR_VALUES = {"sigma0", "sigma2", "sigma_ref", "edge_weight"}
EARLIER_FAMILY = "structured_light"


def migrate_flat(d: dict) -> dict:
    """A settings mapping in the current layout: the flat layout's names (`FLAT_NAMES`) move into
    their groups, its boolean ``free_space`` becomes ``free_space.enabled``, and a ``sensor`` group
    with every noise value but no family (written before the families) gets `EARLIER_FAMILY`.
    Current-layout input is returned unchanged."""
    out = {k: v for k, v in d.items() if k not in FLAT_NAMES}
    groups: dict[str, dict] = {}
    if isinstance(out.get("free_space"), bool):
        groups["free_space"] = {"enabled": out.pop("free_space")}
    for old, new in FLAT_NAMES.items():
        if old in d:
            group, name = new.split(".")
            groups.setdefault(group, {})[name] = d[old]
    for group, values in groups.items():
        given = out.get(group)
        if isinstance(given, dict):  # a group of the current layout beside one of its flat names
            if both := sorted(set(given) & set(values)):
                raise ValueError(f"{group}: given both as a group and as flat settings ({both})")
            values = {**given, **values}
        out[group] = values
    sensor = out.get("sensor")
    if isinstance(sensor, dict) and "family" not in sensor and EARLIER_SENSOR_VALUES <= set(sensor):
        out["sensor"] = {**sensor, "family": EARLIER_FAMILY}
    return out
