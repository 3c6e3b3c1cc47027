#!/usr/bin/env python3
"""Write the service's OpenAPI document to ``openapi/openapi.json`` (or check it is current with --check).

    python scripts/export_openapi.py           # regenerate
    python scripts/export_openapi.py --check   # exit 1 when the checked-in file is stale
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "openapi" / "openapi.json"


def render() -> str:
    """The OpenAPI JSON of ``service.main.create_app()`` (no model is loaded: the lifespan does not run)."""
    sys.path.insert(0, str(ROOT))
    from service.main import create_app

    return json.dumps(create_app().openapi(), indent=2, sort_keys=True) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="fail if openapi/openapi.json is out of date")
    args = parser.parse_args()
    text = render()
    if args.check:
        if not OUT.is_file() or OUT.read_text() != text:
            print(f"{OUT} is stale: run `python scripts/export_openapi.py`", file=sys.stderr)
            return 1
        print(f"{OUT} is up to date")
        return 0
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(text)
    print(f"wrote {OUT}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
