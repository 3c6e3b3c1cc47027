"""Radar world simulator: persistent tile-based worlds, a Navtech-like sensor model, dataset writers and the
named benchmark suites (``build_suite``). See docs/SIMULATOR.md."""

from reradar_core.sim.sensor import SensorConfig, render_scan, scan_seed
from reradar_core.sim.suites import SUITES, SuiteData, build_suite, suite_names
from reradar_core.sim.traversal import CONDITIONS, Condition, Traversal
from reradar_core.sim.world import PROFILES, Primitives, RoadNetwork, World, WorldProfile

__all__ = [
    "CONDITIONS",
    "Condition",
    "PROFILES",
    "Primitives",
    "RoadNetwork",
    "SUITES",
    "SensorConfig",
    "SuiteData",
    "Traversal",
    "World",
    "WorldProfile",
    "build_suite",
    "render_scan",
    "scan_seed",
    "suite_names",
]
