"""Run ``reradar bench`` on the evaluation suites and collect the tables and figures for docs/BENCHMARKS.md.

    nice -n 5 python benchmarks/run_bench_suites.py [--suites boreas-sim loop-sim loop-sim-hard offroad-sim offroad-sim-hard] [--methods ...]

Each suite's results go to ``cache_dir("bench", <suite>)`` (results.json, results.md, PNGs, per-query
arrays); its figures are copied to ``docs/img/bench_<suite>_<figure>.png``, and the combined markdown is
written to ``cache_dir("bench")/ALL.md`` for pasting into the docs. Features are cached, so re-running after
new weights only recomputes the ReRadar models.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
from pathlib import Path

from reradar_core.paths import cache_dir

REPO = Path(__file__).resolve().parents[1]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--suites", nargs="+", default=["boreas-sim", "loop-sim", "loop-sim-hard", "offroad-sim", "offroad-sim-hard"])
    ap.add_argument("--methods", default=None, help="comma-separated (default: all)")
    ap.add_argument("--collect-only", action="store_true", help="do not run; collect existing outputs")
    ap.add_argument("--extra", nargs=argparse.REMAINDER, default=[], help="more `reradar bench` options")
    args = ap.parse_args()
    parts = []
    for suite in args.suites:
        out = cache_dir("bench", suite)
        cmd = ["reradar", "bench", "--suite", suite, "--out", str(out)]
        if args.methods:
            cmd += ["--methods", args.methods]
        cmd += args.extra
        if not args.collect_only:
            print("$", " ".join(cmd), flush=True)
            rc = subprocess.call(cmd)
            if rc != 0:
                print(f"{suite}: reradar bench failed with exit code {rc}", file=sys.stderr)
                return rc
        img = REPO / "docs" / "img"
        img.mkdir(parents=True, exist_ok=True)
        links = []
        for png in sorted(out.glob("*.png")):
            target = img / f"bench_{suite}_{png.name}"
            shutil.copyfile(png, target)
            links.append(f"![{suite} {png.stem}](img/{target.name})")
        md = (out / "results.md").read_text().replace("# `reradar bench` results", "#### `reradar bench` results")
        md = md.replace("\n### ", "\n##### ")
        parts.append(md + "\n" + "\n".join(links) + "\n")
    (cache_dir("bench") / "ALL.md").write_text("\n\n".join(parts))
    print(f"wrote {cache_dir('bench') / 'ALL.md'} and docs/img/bench_*.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
