"""Plausibility bounds on input values, shared by the library and the service's request models.

No imports beyond the standard library: the vehicle-side client (``service.client``, through
``service.api.schemas``) loads this module and must stay free of OpenCV, torch and FAISS.
"""

from __future__ import annotations

__all__ = ["MAX_ABS_COORDINATE_M"]

#: Largest accepted |x| and |y| of a position, metres: pose files (``reradar_core.io.poses``), keyframe poses of
#: a map (``maps.store``) and the request priors of ``POST /localize``. UTM northings stay below 1e7 m.
MAX_ABS_COORDINATE_M = 1e7
