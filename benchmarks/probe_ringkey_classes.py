"""Which simulated objects make RingKey's rings change faster per metre than on real scans? (a probe, session 13)

Renders the eleven real Oxford poses (the same stretch and three world seeds as
``benchmarks/descriptor_decorrelation.py``) with one class of primitives left out at a time (by patching
``World.query`` / ``Traversal.dynamic_primitives`` in this process only) and prints, against the real scans: the mean
of RingKey's five nearest rings (2.6-9.3 m), their mean change between scans 1.9 m apart, and RingKey's mean distance
between those scans (docs/SIMULATOR.md, "Descriptor change per metre driven").

    OPENBLAS_NUM_THREADS=1 python benchmarks/probe_ringkey_classes.py ../shared/data/real-oxford
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from dataclasses import fields
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from descriptor_decorrelation import real_stretch, render_at  # noqa: E402

from reradar_core.baselines.ringkey import ring_key  # noqa: E402
from reradar_core.io.scan import RadarScan  # noqa: E402
from reradar_core.sim.traversal import Traversal  # noqa: E402
from reradar_core.sim.world import Primitives, RoadNetwork, World  # noqa: E402

_SEG = ("seg", "seg_refl", "seg_trans", "seg_rough", "seg_low")
_PTS = ("pts", "pts_rcs", "pts_kind")
Patch = Callable[[Primitives], Primitives]


def _keep(p: Primitives, names: tuple[str, ...], keep: np.ndarray) -> Primitives:
    out = Primitives(**{f.name: getattr(p, f.name) for f in fields(p)})
    for name in names:
        setattr(out, name, getattr(p, name)[keep])
    return out


def _no_cars(p: Primitives) -> Primitives:  # vehicles are the dynamic segments of roughness 0.5
    return _keep(p, _SEG, p.seg_rough != 0.5)


def _low_cars(p: Primitives) -> Primitives:
    p.seg_low = np.where(p.seg_rough == 0.5, 1.0, p.seg_low)
    return p


def _no_points(kind: int) -> Patch:
    return lambda p: _keep(p, _PTS, p.pts_kind != kind)


def _same(p: Primitives) -> Primitives:
    return p


# name -> (patch of the static world's primitives, patch of the traversal's dynamic ones)
VARIANTS: dict[str, tuple[Patch, Patch]] = {
    "v7 (nothing left out)": (_same, _same),
    "no cars (parked and moving)": (_same, _no_cars),
    "cars lit like kerbs (ground elevation pattern)": (_same, _low_cars),
    "no kerbs (the low static segments)": (lambda p: _keep(p, _SEG, p.seg_low == 0), _same),
    "no hard points (poles, facade details, posts)": (_no_points(0), _same),
    "no leaf points": (_no_points(1), _same),
    "no ground points": (_no_points(2), _same),
    "no cars and no hard points": (_no_points(0), _no_cars),
}


def near_ring_figures(scans: list[RadarScan]) -> tuple[float, float, float]:
    """(mean of the 5 nearest rings, their mean |change| between consecutive scans, mean RingKey distance)."""
    k = np.stack([ring_key(s.power) for s in scans])
    diff = np.diff(k, axis=0)
    return float(k[:, :5].mean()), float(np.abs(diff[:, :5]).mean()), float(np.sqrt((diff**2).sum(1)).mean())


def main() -> None:
    if len(sys.argv) != 2:
        raise SystemExit(__doc__)
    real, traj, frames = real_stretch(Path(sys.argv[1]))
    ref = near_ring_figures([real.load_scan(i) for i in range(len(real))])
    print("| scans | rings 0-4 mean | their change per 1.9 m | RingKey distance per 1.9 m (x real) |")
    print("|---|---|---|---|")
    print(f"| real Oxford | {ref[0]:.4f} | {ref[1]:.4f} | {ref[2]:.4f} |")
    query, dynamic = World.query, Traversal.dynamic_primitives
    try:
        for name, (static_patch, dynamic_patch) in VARIANTS.items():
            def patched_query(self: World, c: np.ndarray, r: float, f: Patch = static_patch) -> Primitives:
                return f(query(self, c, r))

            def patched_dynamic(self: Traversal, t: float, c: np.ndarray, r: float, s: Primitives,
                                f: Patch = dynamic_patch) -> Primitives:
                return f(dynamic(self, t, c, r, s))

            World.query = patched_query  # type: ignore[method-assign,assignment]
            Traversal.dynamic_primitives = patched_dynamic  # type: ignore[method-assign,assignment]
            per_world = []
            for w in (1, 2, 3):
                trav = Traversal(World(RoadNetwork([traj.xy]), seed=w, profile="urban"), w + 1, "clear")
                per_world.append(near_ring_figures(render_at(trav, traj, real.poses.timestamps_us, frames)))
            m = np.mean(per_world, axis=0)
            print(f"| {name} | {m[0]:.4f} | {m[1]:.4f} | {m[2]:.4f} ({m[2] / ref[2]:.2f}) |")
    finally:
        World.query, Traversal.dynamic_primitives = query, dynamic  # type: ignore[method-assign]


if __name__ == "__main__":
    main()
