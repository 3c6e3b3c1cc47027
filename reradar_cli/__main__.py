"""``python -m reradar_cli`` = ``reradar``."""

from reradar_cli.main import main

if __name__ == "__main__":  # pragma: no cover
    main()
