"""Render the first two scans of every sequence of the given suites with this checkout and compare them byte for
byte with an earlier simulator version's renders in the cache (default v4): the check that a simulator change
left those suites as they were (docs/SIMULATOR.md).

    RERADAR_CACHE_DIR=... python benchmarks/verify_sim_identity.py --against 4 loop-sim offroad-sim train-source
"""

from __future__ import annotations

import argparse
import hashlib
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from reradar_core.paths import cache_dir  # noqa: E402
from reradar_core.sim.suites import build_suite  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("suites", nargs="+")
    ap.add_argument("--against", default="4", help="simulator version of the reference renders")
    ap.add_argument("--trajectory-dir", default=None, help="real Boreas trajectories (Boreas suites)")
    a = ap.parse_args(argv)
    bad = n = 0
    for name in a.suites:
        tmp = Path(tempfile.mkdtemp())
        data = build_suite(name, root=tmp, progress=False, limit=2, trajectory_dir=a.trajectory_dir)
        for out in data.database + data.queries + data.training:
            ref = cache_dir("sim", f"v{a.against}", name) / out.name
            for p in sorted(out.rglob("*.png")):
                q = ref / p.relative_to(out)
                same = q.is_file() and hashlib.md5(q.read_bytes()).digest() == hashlib.md5(p.read_bytes()).digest()
                bad += not same
                n += 1
                print(name, out.name, p.name, "identical" if same else "DIFFERENT", flush=True)
    print(f"{n} scans compared, differences: {bad}")
    return int(bad > 0)


if __name__ == "__main__":
    raise SystemExit(main())
