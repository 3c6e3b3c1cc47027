"""Run the service in a process of its own, for tests that measure its memory or kill it (and for the attack
table in docs/SERVICE.md)::

    python tests/service/fake_server.py --port 8765 --maps-dir DIR [--real-model] [--describe-delay-s 0.2]

Settings come from ``RERADAR_*`` environment variables as in production; ``--api-key`` defaults to the
tests' key. With ``--real-model`` the shipped descriptor model is loaded instead of the fake extractor.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))


def main() -> None:
    from service_test_fakes import API_KEY, FakeExtractor

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--maps-dir", type=Path, required=True)
    parser.add_argument("--api-key", default=API_KEY)
    parser.add_argument("--real-model", action="store_true")
    parser.add_argument("--describe-delay-s", type=float, default=0.0,
                        help="sleep per described scan (slow map builds for the crash tests)")
    args = parser.parse_args()

    import uvicorn

    from service.core.config import Settings
    from service.main import create_app

    extractor = None
    if not args.real_model:
        extractor = FakeExtractor()
        if args.describe_delay_s > 0:
            describe = extractor.describe

            def slow(scan):  # type: ignore[no-untyped-def]
                time.sleep(args.describe_delay_s)
                return describe(scan)

            extractor.describe = slow  # type: ignore[method-assign]
    os.environ.setdefault("RERADAR_LOAD_DEMO_MAP", "false")
    settings = Settings(maps_dir=args.maps_dir, api_key=args.api_key)
    uvicorn.run(create_app(settings, extractor), host="127.0.0.1", port=args.port, log_level="warning",
                access_log=False)


if __name__ == "__main__":
    main()
