"""One service process for the fleet tests, with the tests' fast fake extractor (settings from RERADAR_*).

    python tests/service/ops_replica.py api PORT     # an API replica on 127.0.0.1:PORT
    python tests/service/ops_replica.py worker       # a map-build worker

``OPS_FAKE_SCAN_DELAY_S`` slows the worker's extractor down per scan, so a test can kill it mid-build.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))


def main() -> None:
    import os

    from service_test_fakes import FakeExtractor

    from service.core.config import Settings

    class SlowFakeExtractor(FakeExtractor):
        delay_s = float(os.environ.get("OPS_FAKE_SCAN_DELAY_S", "0"))

        def describe_batch(self, scans):  # type: ignore[no-untyped-def]
            time.sleep(self.delay_s * len(scans))
            return super().describe_batch(scans)

    mode = sys.argv[1]
    settings = Settings()
    if mode == "api":
        import uvicorn

        from service.main import create_app

        uvicorn.run(create_app(settings, SlowFakeExtractor()), host="127.0.0.1", port=int(sys.argv[2]),
                    log_level="warning", access_log=False)
    elif mode == "worker":
        from service.worker import run_worker

        run_worker(settings, SlowFakeExtractor())
    else:
        raise SystemExit(f"unknown mode {mode!r}")


if __name__ == "__main__":
    main()
