"""Pose file readers/writers: Boreas (ns and µs GPSTime), MulRan, plain t,x,y,yaw; errors name file and line."""

from __future__ import annotations

import numpy as np
import pytest

from reradar_core.errors import PoseFileError
from reradar_core.io.poses import (
    BOREAS_COLUMNS,
    PoseSequence,
    read_boreas_radar_poses,
    read_mulran_global_pose,
    read_poses,
    read_txyyaw_csv,
    write_boreas_radar_poses,
    write_mulran_global_pose,
    write_txyyaw_csv,
)

HEADER = ",".join(BOREAS_COLUMNS)
# Same shapes as the two real Boreas files: GPSTime in nanoseconds (2021-08-05) and in microseconds (2021-09-02).
BOREAS_NS = HEADER + """
1628184886551599081,623425.5464750652,4848820.9989206735,154.06,-0.0007,-0.0008,-0.0001,3.1313,0.0197,0.2367720262139094,6.8e-05,-0.0008,-0.0049
1628184886801550666,623425.5464652807,4848820.998891991,154.06,0.0005,-0.0007,-0.0001,3.1312,0.0197,0.23675085346175226,-0.0008,-0.0062,0.0008
1628184887051601000,623427.0,4848822.5,154.06,0.0,0.0,0.0,3.13,0.019,-3.0,0.0,0.0,0.0
"""
BOREAS_US = HEADER + """
1630597331060160,623422.8507264568,4848820.469537824,153.97,-0.0002,0.0002,7.4e-05,3.1262,0.0318,0.25671182385755154,0.0013,-0.0057,0.0011
1630597331310779,623422.8507496119,4848820.469538635,153.97,-0.0007,0.0004,-0.0004,3.1262,0.0319,0.25673404594601285,0.0015,-0.0006,0.0005
"""


def _write(tmp_path, name: str, text: str):
    p = tmp_path / name
    p.write_text(text.lstrip("\n"))
    return p


def test_boreas_nanosecond_gpstime(tmp_path):
    poses = read_boreas_radar_poses(_write(tmp_path, "radar_poses.csv", BOREAS_NS))
    assert len(poses) == 3
    np.testing.assert_array_equal(poses.timestamps_us, [1628184886551599, 1628184886801550, 1628184887051601])
    np.testing.assert_allclose(poses.xy[0], [623425.5464750652, 4848820.9989206735])
    np.testing.assert_allclose(poses.yaw[:2], [0.2367720262139094, 0.23675085346175226])
    assert poses.yaw[2] == pytest.approx(-3.0)


def test_boreas_microsecond_gpstime(tmp_path):
    poses = read_boreas_radar_poses(_write(tmp_path, "radar_poses.csv", BOREAS_US))
    np.testing.assert_array_equal(poses.timestamps_us, [1630597331060160, 1630597331310779])
    np.testing.assert_allclose(poses.xy[1], [623422.8507496119, 4848820.469538635])
    assert poses.yaw[0] == pytest.approx(0.25671182385755154)


def test_read_poses_dispatches_on_first_line(tmp_path):
    assert len(read_poses(_write(tmp_path, "a.csv", BOREAS_US))) == 2
    assert len(read_poses(_write(tmp_path, "b.csv", "t,x,y,yaw\n1.5,2,3,0.1\n2.5,3,4,0.2\n"))) == 2
    mulran = "1566535872045000000,1,0,0,10,0,1,0,20,0,0,1,0\n"
    assert read_poses(_write(tmp_path, "c.csv", mulran)).timestamps_us[0] == 1566535872045000
    with pytest.raises(PoseFileError, match="c2.csv:1: unrecognised"):
        read_poses(_write(tmp_path, "c2.csv", "a,b\n1,2\n"))


def _random_poses(n: int = 7, seed: int = 0) -> PoseSequence:
    rng = np.random.default_rng(seed)
    t = 1630597331060160 + np.cumsum(rng.integers(200_000, 300_000, n))
    return PoseSequence(t, rng.uniform(-1e3, 1e3, (n, 2)) + [623000.0, 4848000.0], rng.uniform(-np.pi, np.pi, n))


@pytest.mark.parametrize(
    "writer,reader",
    [
        (write_boreas_radar_poses, read_boreas_radar_poses),
        (write_mulran_global_pose, read_mulran_global_pose),
        (write_txyyaw_csv, read_txyyaw_csv),
    ],
)
def test_writer_reader_round_trip(tmp_path, writer, reader):
    poses = _random_poses()
    back = reader(writer(poses, tmp_path / "poses.csv"))
    np.testing.assert_array_equal(back.timestamps_us, poses.timestamps_us)
    np.testing.assert_allclose(back.xy, poses.xy, atol=1e-6)
    np.testing.assert_allclose(np.cos(back.yaw - poses.yaw), 1.0, atol=1e-12)
    # read_poses recognises every format it writes
    again = read_poses(tmp_path / "poses.csv")
    np.testing.assert_array_equal(again.timestamps_us, poses.timestamps_us)


def test_mulran_rotation_gives_yaw(tmp_path):
    yaw = 2.5
    c, s = np.cos(yaw), np.sin(yaw)
    line = f"1000,{c},{-s},0,5.0,{s},{c},0,-7.0,0,0,1,0.5\n"
    poses = read_mulran_global_pose(_write(tmp_path, "global_pose.csv", line))
    assert poses.yaw[0] == pytest.approx(yaw)
    np.testing.assert_allclose(poses.xy[0], [5.0, -7.0])
    assert poses.timestamps_us[0] == 1  # ns -> µs


def test_malformed_boreas_names_file_and_line(tmp_path):
    bad = BOREAS_US.replace("623422.8507496119", "oops")
    with pytest.raises(PoseFileError, match=r"bad\.csv:3: non-numeric"):
        read_boreas_radar_poses(_write(tmp_path, "bad.csv", bad))
    short = HEADER + "\n1630597331060160,1,2\n"
    with pytest.raises(PoseFileError, match=r"short\.csv:2: expected at least 10 columns"):
        read_boreas_radar_poses(_write(tmp_path, "short.csv", short))
    nan = BOREAS_US.replace("0.25673404594601285", "nan")
    with pytest.raises(PoseFileError, match=r"nan\.csv:3: NaN"):
        read_boreas_radar_poses(_write(tmp_path, "nan.csv", nan))


def test_malformed_other_formats(tmp_path):
    with pytest.raises(PoseFileError, match=r"t\.csv:3: non-numeric"):
        read_txyyaw_csv(_write(tmp_path, "t.csv", "t,x,y,yaw\n1,2,3,4\n2,x,3,4\n"))
    with pytest.raises(PoseFileError, match=r"m\.csv:2: timestamp 'abc'"):
        read_mulran_global_pose(_write(tmp_path, "m.csv", "1,1,0,0,0,0,1,0,0,0,0,1,0\nabc,1,0,0,0,0,1,0,0,0,0,1,0\n"))
    with pytest.raises(PoseFileError, match="no pose rows"):
        read_txyyaw_csv(_write(tmp_path, "empty.csv", "t,x,y,yaw\n"))
    with pytest.raises(PoseFileError, match="no such pose file"):
        read_poses(tmp_path / "missing.csv")


def test_pose_sequence_interpolation_wraps_yaw():
    seq = PoseSequence([0, 100], [[0.0, 0.0], [10.0, -2.0]], [np.pi - 0.1, -np.pi + 0.1])
    mid = seq.interpolate(50)
    np.testing.assert_allclose(mid[:2], [5.0, -1.0])
    assert abs(abs(mid[2]) - np.pi) < 1e-9  # halfway across the +-pi seam, not through 0
    np.testing.assert_allclose(seq.interpolate(np.array([-10, 500]))[:, 0], [0.0, 10.0])  # clamped
