"""Where the shipped demo map and demo queries live (``maps/demo``)."""

from __future__ import annotations

from pathlib import Path

__all__ = ["DEMO_DIR", "DEMO_MAP_PATH", "DEMO_QUERIES_DIR"]

DEMO_DIR = Path(__file__).resolve().parent / "demo"
DEMO_MAP_PATH = DEMO_DIR / "demo.h5"
DEMO_QUERIES_DIR = DEMO_DIR / "queries"
