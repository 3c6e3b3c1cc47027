"""Keyframe map store: HDF5 maps (``store``), the FAISS global-descriptor index (``index``), retrieval and
localization against a loaded map (``database``), map building (``build``) and the ``reradar build-map``
command (``cli``). A small demo map ships in ``maps/demo`` (paths in ``maps.paths``)."""

from __future__ import annotations

from maps.paths import DEMO_DIR, DEMO_MAP_PATH, DEMO_QUERIES_DIR

__all__ = ["DEMO_DIR", "DEMO_MAP_PATH", "DEMO_QUERIES_DIR"]
