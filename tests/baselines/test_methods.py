"""Every baseline and variant: finds the revisited place, is rotation-invariant where its reference is, and
the heading estimators recover a known heading offset."""

from __future__ import annotations

import numpy as np
import pytest

from reradar_core.baselines import BASELINES, VARIANTS, make_method
from reradar_core.benchmark.rotation import rotate_scan
from reradar_core.errors import ConfigError

# The OORD reference RaPlace correlates along the frequency axis only, so a turned scan is not its own
# nearest neighbour there; the raplace-nodc variant correlates over angle shifts and is.
ROTATION_INVARIANT = ("ringkey", "raplace-nodc", "radvlad", "radvlad-half", "referee")


def _rank(method, db_scans, query_scan):
    prepared = [method.prepare(s) for s in db_scans]
    method.fit(prepared)
    index = method.build_index([method.describe_prepared(p) for p in prepared])
    q = method.describe(query_scan)
    return method.distance(q, index), q, index


@pytest.mark.parametrize("name", BASELINES + VARIANTS)
def test_revisit_is_the_nearest_database_entry(name, scans):
    scan_list, _ = scans
    method = make_method(name)
    d, _, _ = _rank(method, scan_list[:5], scan_list[5])
    assert d.shape == (5,)
    assert int(np.argmin(d)) == 0, f"{name}: distances {np.round(d, 4)}"


@pytest.mark.parametrize("name", ROTATION_INVARIANT)
def test_rotation_invariant_methods_still_find_a_turned_revisit(name, scans):
    scan_list, _ = scans
    method = make_method(name)
    turned = rotate_scan(scan_list[5], np.deg2rad(137.7))
    d, _, _ = _rank(method, scan_list[:5], turned)
    assert int(np.argmin(d)) == 0, f"{name}: distances {np.round(d, 4)}"


# ReFeree's heading comes in 7.2 degree sectors (50 for 400 azimuths): exact on sector multiples, within half
# a sector otherwise; RaPlace's in 1 degree projection steps.
@pytest.mark.parametrize(("name", "yaw_deg", "tol_deg"), [("referee", 43.2, 0.5), ("referee", -115.2, 0.5),
                                                          ("referee", 40.5, 3.6), ("raplace-nodc", 36.0, 1.0),
                                                          ("raplace-nodc", -63.0, 1.0)])
def test_heading_estimate_recovers_a_known_turn(name, yaw_deg, tol_deg, scans):
    """Query = database scan 1 turned by yaw (CCW): the estimated yaw of T_db_query is that yaw."""
    scan_list, _ = scans
    method = make_method(name)
    turned = rotate_scan(scan_list[1], np.deg2rad(yaw_deg))
    d, q, index = _rank(method, scan_list[:5], turned)
    assert int(np.argmin(d)) == 1
    est = np.rad2deg(method.estimate_heading(q, index, 1))
    assert abs((est - yaw_deg + 180) % 360 - 180) <= tol_deg, est


def test_methods_without_heading_return_none(scans):
    scan_list, _ = scans
    for name in ("ringkey", "raplace", "radvlad", "radvlad-half", "resnet18-netvlad"):
        m = make_method(name)
        assert not m.provides_heading and not m.provides_pose
        _, q, index = _rank(m, scan_list[:3], scan_list[5])
        assert m.estimate_heading(q, index, 0) is None


def test_unknown_method_is_a_config_error():
    with pytest.raises(ConfigError, match="unknown method"):
        make_method("scan-context-9000")


def test_cache_keys_differ_between_methods_and_parameters():
    from reradar_core.baselines.ringkey import RingKey, RingKeyConfig

    keys = {make_method(n).cache_key for n in BASELINES + VARIANTS}
    assert len(keys) == len(BASELINES + VARIANTS)
    assert RingKey().cache_key != RingKey(RingKeyConfig(num_rings=60)).cache_key


def test_cache_key_changes_with_the_algorithm_version():
    """Same name and parameters, new algorithm: cached records of the old one must not be found."""
    from reradar_core.baselines.ringkey import RingKey

    class RingKeyNext(RingKey):
        algorithm_version = RingKey.algorithm_version + 1

    assert RingKeyNext().params() == RingKey().params()
    assert RingKeyNext().cache_key != RingKey().cache_key
    assert RingKey().cache_key.endswith(f"-a{RingKey.algorithm_version}")


def test_fit_needed_before_describe_for_vocabulary_methods(scans):
    scan_list, _ = scans
    for name in ("radvlad", "radvlad-half", "resnet18-netvlad"):
        m = make_method(name)
        with pytest.raises(ConfigError, match="fit"):
            m.describe(scan_list[0])
