"""Where the shipped demo map and demo queries live (``maps/demo``)."""

from __future__ import annotations

from pathlib import Path

__all__ = ["DEMO_DIR", "DEMO_MAP_PATH", "DEMO_QUERIES_DIR", "FAR_VIEW_SUFFIX", "far_view_path"]

DEMO_DIR = Path(__file__).resolve().parent / "demo"
DEMO_MAP_PATH = DEMO_DIR / "demo.h5"
DEMO_QUERIES_DIR = DEMO_DIR / "queries"

#: Suffix of a map's far-view companion file (``<map>.far.h5``): the same keyframes described in ReRadar's far view
#: (``reradar_core.localization.far_view``), a complete map of its own under the far view's model id.
FAR_VIEW_SUFFIX = ".far.h5"


def far_view_path(map_path: str | Path) -> Path:
    """The far-view companion of the map file ``map_path`` (``x.h5`` -> ``x.far.h5``)."""
    path = Path(map_path)
    return path.with_name(path.stem + FAR_VIEW_SUFFIX)
