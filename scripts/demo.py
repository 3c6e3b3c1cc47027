#!/usr/bin/env python3
"""The README demo (same as `reradar demo`): serve the shipped demo map on a real uvicorn server on localhost,
localize the demo query scans over HTTP, print poses, ground truth and errors, then stop the server."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from service.demo import run_demo  # noqa: E402

if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    raise SystemExit(run_demo(threads=args.threads))
