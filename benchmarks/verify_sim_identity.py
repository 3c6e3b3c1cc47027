"""Render the first two scans of every sequence of the given suites, and ``--spread`` scans spread along each drive
(default 6), with this checkout and compare them byte for byte with an earlier simulator version's renders in the
cache (default v4): the check that a simulator change left those suites as they were (docs/SIMULATOR.md). The
spread scans (session 32) catch a change confined to one part of a world, which the first scans can miss.

    RERADAR_CACHE_DIR=... python benchmarks/verify_sim_identity.py --against 4 loop-sim offroad-sim train-source

With ``--carry-over``, every suite whose compared scans are all identical is taken over into the current
version's cache instead of being rendered again: each complete sequence folder of the old version is copied as
hard links (no extra disk; the old cache is not modified), and its completion marker, render-version file and
``reradar_sim.json`` are written anew for the current version, the latter with a ``carried_over_from`` note.
A suite with any difference, or a sequence already complete in the current version, is left alone.
"""

from __future__ import annotations

import argparse
import hashlib
import math
import shutil
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from reradar_core.paths import cache_dir  # noqa: E402
from reradar_core.sim.suites import SUITES, build_suite  # noqa: E402
from reradar_core.sim.writer import SIM_VERSION, carry_over  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("suites", nargs="+")
    ap.add_argument("--against", default="4", help="simulator version of the reference renders")
    ap.add_argument("--trajectory-dir", default=None, help="real Boreas trajectories (Boreas suites)")
    ap.add_argument("--spread", type=int, default=6,
                    help="also compare this many scans spread along every drive (0 = the first two only)")
    ap.add_argument("--carry-over", action="store_true",
                    help="take identical suites over into the current version's cache (hard links)")
    a = ap.parse_args(argv)
    bad = n = 0
    for name in a.suites:
        old_root = cache_dir("sim", f"v{a.against}", name)
        suite_bad = 0
        outs: list[Path] = []
        # the first scans of every sequence, then scans spread along every drive (session 32: a change confined
        # to one part of a world, e.g. open land, leaves the first scans alike): the sequences' common frame step
        # times m, so every spread scan is one the old render holds
        defs = SUITES[name].sequences
        step = math.lcm(*(d.every for d in defs))
        frames = min((len(list((old_root / d.name).rglob("*.png"))) * d.every for d in defs
                      if (old_root / d.name).is_dir()), default=0)
        passes = [(None, 2)] + ([(step * max(1, frames // (step * a.spread)), a.spread)] if a.spread else [])
        for every, limit in passes:
            tmp = Path(tempfile.mkdtemp())
            data = build_suite(name, root=tmp, progress=False, every=every, limit=limit,
                               trajectory_dir=a.trajectory_dir)
            outs = data.database + data.queries + data.training + data.confidence
            for out in outs:
                ref = old_root / out.name
                for p in sorted(out.rglob("*.png")):
                    q = ref / p.relative_to(out)
                    same = q.is_file() and hashlib.md5(q.read_bytes()).digest() == hashlib.md5(p.read_bytes()).digest()
                    suite_bad += not same
                    n += 1
                    print(name, out.name, p.name, "identical" if same else "DIFFERENT", flush=True)
            shutil.rmtree(tmp, ignore_errors=True)
        bad += suite_bad
        if a.carry_over and not suite_bad and SIM_VERSION != a.against:
            new_root = cache_dir("sim", f"v{SIM_VERSION}", name)  # creates the folder: only when carrying over
            for out in outs:
                done = carry_over(old_root / out.name, new_root / out.name, a.against)
                print(name, out.name, f"carried over v{a.against} -> v{SIM_VERSION}" if done else "not carried over")
    print(f"{n} scans compared, differences: {bad}")
    return int(bad > 0)


if __name__ == "__main__":
    raise SystemExit(main())
