"""ReRadar core library: radar scan I/O, geometry, landmarks, learned descriptors, matching, RANSAC,
metrics, training, the radar simulator, baselines and the benchmark harness.

Conventions (also in docs/CONVENTIONS.md):
- Sensor/vehicle frame: x forward, y left, z up; yaw counter-clockwise positive, radians inside the library.
- Navtech azimuth a is measured clockwise from +x (the antenna spins clockwise seen from above), so a return
  at azimuth a and range r sits at x = r cos a, y = -r sin a in the sensor frame.
- Poses are T_world_sensor = (x, y, yaw) in metres / radians; ``T_a_b`` maps points from frame b to frame a.
"""

import logging

__version__ = "0.1.0"
__all__ = ["__version__"]

logging.getLogger(__name__).addHandler(logging.NullHandler())
