"""Which sensor family `auto` detects on each capture, frame by frame, and the voxel size a session
without one chooses from its first frame.

    python bench/sensor_families.py [../shared/data/realsense_shelf ...]   (default: every capture there)

Per capture: the frames, how many frames each family is detected on (`config.detect_family`: depth
levels c z^2 apart, the disparity quantisation of structured light and active stereo), the range of
c where one is found, the family and reason a session's first frame gives, and the voxel size it
chooses (`scene.choices.default_voxel_size`: 6 pixel footprints at that frame's median depth). A
session decides on its first frame alone, so every frame of a capture should give the same answer.
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import print_table  # noqa: E402

from canonical_core.config import detect_family, disparity_step  # noqa: E402
from canonical_core.datasets import load_dataset  # noqa: E402
from canonical_core.scene.choices import default_voxel_size  # noqa: E402

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
CAPTURES = ("realsense_shelf", "sun3d_studyroom", "hololens_office", "apc_bins/bin_labels", "apc_bins/bin_mask",
            "livingroom_synthetic")


def row(path: Path) -> dict:
    """The detection on every frame of the capture at ``path``, and its first frame's choices."""
    sequence = load_dataset(path)
    families, steps = Counter(), []
    for k in range(len(sequence)):
        depth = sequence[k].depth
        family, why = detect_family(depth)
        families[f"{family} ({why.split(':')[0].split(' ')[0]})"] += 1  # "detected" or "default"
        steps.append(disparity_step(depth) if depth is not None else None)
    found = [s for s in steps if s is not None]
    family, why = detect_family(sequence[0].depth)
    return {"capture": str(path.relative_to(DATA)) if path.is_relative_to(DATA) else str(path),
            "frames": len(sequence), "detected per frame": ", ".join(f"{f} {n}" for f, n in families.most_common()),
            "c (1/m)": f"{min(found):.3g}-{max(found):.3g}" if found else "-",
            "first frame": f"{family} ({why})",
            "voxel (first frame)": f"{default_voxel_size([sequence[0]]) * 1000:g} mm"}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("captures", nargs="*", type=Path,
                        help="capture folders (default: every capture in ../shared/data)")
    args = parser.parse_args()
    paths = args.captures or [DATA / name for name in CAPTURES if (DATA / name).is_dir()]
    print_table("Sensor family detected from depth quantisation", [row(p) for p in paths])
    return 0


if __name__ == "__main__":
    sys.exit(main())
