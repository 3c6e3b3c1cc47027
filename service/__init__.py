"""ReRadar HTTP service (FastAPI): upload scans, retrieve keyframes, localize, register maps.

Thin layer over ``reradar_core`` and ``maps``; build the app with ``service.main.create_app``.
"""
