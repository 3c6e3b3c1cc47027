"""A canonical heading for a polar scan: the turn that makes the global descriptor invariant at any angle.

The C8 network is exactly invariant to 90-degree turns of its input image and only approximately between them
(docs/MODEL.md, "Invariance at any angle"). Turning the sensor is an exact relabelling of the scan's azimuths, so a
heading read from the polar scan by a rule that turns with the scan (rotation-*equivariant*), taken modulo 90
degrees, brings every scan to the same canonical heading before the Cartesian image is made: a scan and any turned
copy of it give the same image and the same descriptor (as SIFT's dominant orientation does for patches).

The rule: the phase of the fourth azimuthal harmonic of the beam profile,

    psi = arg( sum_a p(a) exp(4 i a) ) / 4,    p(a) = mean squared power of beam a over ranges (2 m, max_range_m],

(a = the beam's azimuth, clockwise; squared so that strong returns, the walls and banks that stay from one pass to
the next, outweigh clutter: on the training splits' validation tails it kept every query the plain image found,
where the mean power lost one in 64-83 off-road and on open loops; docs/MODEL.md, "A canonical heading"). A sensor yawed counter-clockwise by theta labels every beam a + theta, so psi
becomes psi + theta (mod 90 deg), and the sensor turned by ``-psi`` sees the scene at one canonical heading. The
fourth harmonic because the network already takes care of the 90-degree steps, and because streets, walls and
field edges meet mostly at right angles. Frames: azimuths clockwise from the sensor's +x, yaw counter-clockwise
(docs/CONVENTIONS.md).

Used by the descriptor when ``ModelConfig.canonical_heading`` is on, which it is **not** by default: a turned copy of
a scan then gets exactly its descriptor (cosine >= 0.9999 at any angle, where the network alone gives 0.70-0.86), but
the heading read from two passes of one place differs by a median 4-10 degrees (parallax and changed returns move
the beam profile), and on an open urban loop that cost the descriptor alone 9.7 points of Recall@1 (docs/MODEL.md,
"A canonical heading").
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from reradar_core.io.scan import RadarScan

__all__ = ["canonical_turn", "turn_scan", "MIN_PROFILE_RANGE_M"]

#: Returns nearer than this are left out of the beam profile (the sensor's own ring and mount).
MIN_PROFILE_RANGE_M = 2.0


def canonical_turn(scan: RadarScan, max_range_m: float) -> float:
    """The counter-clockwise turn (radians, in [-pi/4, pi/4]) that brings the sensor to its canonical heading.

    Args:
        scan: the polar scan; power (A, R), azimuths (A,) radians clockwise.
        max_range_m: the beam profile's outer range (the Cartesian image's half width: what the network sees).

    Returns:
        ``-psi`` (see the module docstring): ``turn_scan(scan, canonical_turn(scan, r))`` is the canonical scan.
        0.0 for a scan with no structure at the fourth harmonic (an empty or rotationally uniform scan).
    """
    r = scan.range_offset_m + scan.range_resolution_m * np.arange(scan.num_range_bins)
    use = (r > MIN_PROFILE_RANGE_M) & (r <= max_range_m)
    if not use.any():
        return 0.0
    lo, hi = int(np.argmax(use)), int(len(use) - np.argmax(use[::-1]))
    beams = scan.power[:, lo:hi].astype(np.float64)
    profile = np.einsum("ij,ij->i", beams, beams) / beams.shape[1]
    z = np.sum(profile * np.exp(4j * np.asarray(scan.azimuths, np.float64)))
    if not np.isfinite(z) or abs(z) <= 1e-12 * max(float(np.abs(profile).sum()), 1e-300):
        return 0.0
    return float(-np.angle(z) / 4.0)


def turn_scan(scan: RadarScan, yaw_rad: float) -> RadarScan:
    """The scan as seen by the same sensor yawed counter-clockwise by ``yaw_rad``: every beam relabelled with
    azimuth a + yaw (exact at any angle: no resampling). A point at sensor-frame xy is at ``R(-yaw) xy`` in the
    turned sensor's frame."""
    if yaw_rad == 0.0:
        return scan
    return replace(scan, azimuths=np.mod(np.asarray(scan.azimuths, np.float64) + float(yaw_rad), 2.0 * np.pi))
