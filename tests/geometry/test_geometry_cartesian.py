"""polar_to_cartesian puts a point target at the right pixel (all quadrants, 201 and 200 px, across the seam)."""

from __future__ import annotations

import numpy as np
import pytest

from reradar_core.geometry.cartesian import (
    CartesianConfig,
    metric_to_pixel,
    pixel_to_metric,
    polar_to_cartesian,
    polar_to_metric,
)
from reradar_core.io.scan import RadarScan

N_AZ = 400


def _point_target_scan(azimuth_rad: float, range_m: float, preset: str = "oxford",
                       first_azimuth: float = 0.0) -> RadarScan:
    """A blank scan with one bright target spread over +-1 azimuth and +-8 range bins (so bilinear sees it)."""
    scan = RadarScan.from_power(np.zeros((N_AZ, 3768 if preset == "oxford" else 3360), np.float32), preset)
    scan.azimuths = np.mod(first_azimuth + np.arange(N_AZ) * 2 * np.pi / N_AZ, 2 * np.pi)
    step = 2 * np.pi / N_AZ
    rows = np.round((np.mod(azimuth_rad - first_azimuth, 2 * np.pi)) / step).astype(int) + np.array([-1, 0, 1])
    rbin = int(round((range_m - scan.range_offset_m) / scan.range_resolution_m))
    for r in rows % N_AZ:
        scan.power[r, rbin - 8 : rbin + 9] = 1.0
    return scan


def _peak_centroid(img: np.ndarray) -> np.ndarray:
    """(row, col) intensity-weighted centroid of the pixels above half the maximum."""
    m = img >= 0.5 * img.max()
    r, c = np.nonzero(m)
    w = img[m]
    return np.array([np.sum(r * w) / w.sum(), np.sum(c * w) / w.sum()])


@pytest.mark.parametrize("config", [CartesianConfig(), CartesianConfig.paper()], ids=["201px", "200px"])
@pytest.mark.parametrize(
    "xy",
    [(30.0, 20.0), (-25.0, 35.0), (-40.0, -10.0), (15.0, -45.0), (50.0, 0.3), (-0.4, 55.0)],
    ids=["front-left", "back-left", "back-right", "front-right", "ahead", "left"],
)
def test_point_target_lands_at_expected_pixel(config, xy):
    x, y = xy
    azimuth = np.mod(np.arctan2(-y, x), 2 * np.pi)  # clockwise from +x
    rng = float(np.hypot(x, y))
    # the target is drawn on the nearest azimuth row and bin, so predict from that quantised position
    step = 2 * np.pi / N_AZ
    az_q = np.round(azimuth / step) * step
    rng_q = np.round(rng / 0.0432) * 0.0432
    expected = metric_to_pixel(polar_to_metric(np.array([az_q]), np.array([rng_q])), config)[0]
    img = polar_to_cartesian(_point_target_scan(azimuth, rng), config)
    assert img.shape == (config.width_px, config.width_px) and img.dtype == np.float32
    got = _peak_centroid(img)
    assert np.linalg.norm(got - expected) <= 1.0, (got, expected)
    # and the quadrant is right: forward is up (row < centre), left is on the left (col < centre)
    c = config.centre_px
    for offset, coord in ((c - got[0], x), (c - got[1], y)):
        if abs(coord) > 2.0:  # targets on an axis sit on the centre row/column
            assert np.sign(offset) == np.sign(coord)


def test_target_across_the_seam_is_interpolated():
    """Pixels between the last azimuth row and row 0 blend both rows linearly (the seam wraps, no gap)."""
    cfg = CartesianConfig()
    step = 2 * np.pi / N_AZ
    scan = RadarScan.from_power(np.zeros((N_AZ, 3768), np.float32), "oxford")
    rbin = int(round(40.0 / 0.0432))
    scan.power[N_AZ - 1, rbin - 40 : rbin + 41] = 1.0  # azimuth 2 pi - step
    scan.power[0, rbin - 40 : rbin + 41] = 0.5  # azimuth 0 (= 2 pi)
    img = polar_to_cartesian(scan, cfg)
    rows, cols = np.meshgrid(np.arange(cfg.width_px), np.arange(cfg.width_px), indexing="ij")
    xy = pixel_to_metric(np.stack([rows, cols], axis=-1).astype(float), cfg)
    az = np.mod(np.arctan2(-xy[..., 1], xy[..., 0]), 2 * np.pi)
    rng = np.hypot(xy[..., 0], xy[..., 1])
    in_seam = (az > 2 * np.pi - step) & (np.abs(rng - rbin * 0.0432) < 1.0)
    assert in_seam.sum() >= 1
    frac = (az[in_seam] - (2 * np.pi - step)) / step  # 0 at the last row, 1 at row 0
    np.testing.assert_allclose(img[in_seam], 1.0 - 0.5 * frac, atol=0.02)


def test_rotated_first_azimuth_is_honoured():
    """Scans whose first azimuth is not 0 (real encoders) still map targets to their true position."""
    cfg = CartesianConfig()
    x, y = 20.0, -30.0
    azimuth = np.mod(np.arctan2(-y, x), 2 * np.pi)
    first = 0.7
    step = 2 * np.pi / N_AZ
    k = np.round(np.mod(azimuth - first, 2 * np.pi) / step)
    az_q = first + k * step
    rng_q = np.round(np.hypot(x, y) / 0.0432) * 0.0432
    expected = metric_to_pixel(polar_to_metric(np.array([az_q]), np.array([rng_q])), cfg)[0]
    img = polar_to_cartesian(_point_target_scan(azimuth, float(np.hypot(x, y)), first_azimuth=first), cfg)
    assert np.linalg.norm(_peak_centroid(img) - expected) <= 1.0


def test_pixel_metric_round_trip_and_centre():
    for cfg in (CartesianConfig(), CartesianConfig.paper()):
        rng = np.random.default_rng(0)
        xy = rng.uniform(-60, 60, (100, 2))
        np.testing.assert_allclose(pixel_to_metric(metric_to_pixel(xy, cfg), cfg), xy, atol=1e-9)
        np.testing.assert_allclose(metric_to_pixel(np.zeros((1, 2)), cfg), [[cfg.centre_px, cfg.centre_px]])
    # the 201 px image has a pixel centred on the sensor
    assert CartesianConfig().centre_px == 100.0


def test_beyond_range_is_black():
    scan = RadarScan.from_power(np.ones((N_AZ, 3360), np.float32), "boreas")  # max range ~200 m
    img = polar_to_cartesian(scan, CartesianConfig(201, 2.5))  # half-width 251 m
    assert img[100, 100] > 0.99
    assert img[100, 2] == 0.0 and img[0, 0] == 0.0  # 245 m and 354 m from the sensor
    assert img[100, 30] > 0.99  # 175 m


def _uncropped_reference(scan: RadarScan, config: CartesianConfig) -> np.ndarray:
    """``polar_to_cartesian`` as first written: the whole scan handed to remap, the row map computed per call."""
    import cv2

    from reradar_core.geometry.cartesian import _polar_grid

    az, bin_idx, _ = _polar_grid(config.width_px, config.resolution_m, scan.range_resolution_m,
                                 scan.range_offset_m, scan.num_range_bins)
    n_az = scan.num_azimuths
    unwrapped = np.unwrap(scan.azimuths)
    step = (unwrapped[-1] - unwrapped[0]) / (n_az - 1)
    row = np.mod((az - unwrapped[0]) / step, n_az).astype(np.float32)
    polar = np.vstack([scan.power, scan.power[:1]]).astype(np.float32, copy=False)
    return cv2.remap(polar, bin_idx, row, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                     borderValue=0.0)


@pytest.mark.parametrize("config", [CartesianConfig(), CartesianConfig(64, 0.64), CartesianConfig(256, 1.2717),
                                    CartesianConfig(96, 4.0)])
def test_cropped_and_cached_resampling_is_the_same_image(config):
    """Only the range bins the image reaches are resampled, and the row map is cached per azimuth table: the
    same image as remapping the whole scan, bit for bit (images inside and larger than the scan's range)."""
    rng = np.random.default_rng(config.width_px)
    for n_bins, preset in ((3360, "boreas"), (900, "boreas"), (3768, "oxford")):
        power = rng.random((40, n_bins), dtype=np.float32)
        scan = RadarScan.from_power(power, preset)
        first = polar_to_cartesian(scan, config)
        assert first.tobytes() == _uncropped_reference(scan, config).tobytes()
        assert polar_to_cartesian(scan, config).tobytes() == first.tobytes()  # cached row map
        turned = RadarScan.from_power(power, preset)
        turned.azimuths = np.mod(scan.azimuths + 0.3, 2 * np.pi)  # another azimuth table: another row map
        assert polar_to_cartesian(turned, config).tobytes() == _uncropped_reference(turned, config).tobytes()
