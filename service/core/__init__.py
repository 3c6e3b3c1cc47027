"""Service infrastructure: settings, map registry, scan cache, metrics, errors."""
