"""Output folders are checked before a long run starts (``reradar_core.paths``)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from reradar_core.errors import ConfigError
from reradar_core.paths import output_dir, output_file


def test_output_dir_checks_without_leaving_anything(tmp_path: Path) -> None:
    target = tmp_path / "a" / "b"
    assert output_dir(target, create=False) == target
    assert not (tmp_path / "a").exists()
    assert os.listdir(tmp_path) == []  # the writability probe is removed again
    assert output_dir(target).is_dir()


def test_output_dir_refuses_a_file_in_the_way(tmp_path: Path) -> None:
    (tmp_path / "f").write_text("x")
    for create in (False, True):
        with pytest.raises(ConfigError, match="--out-dir .*a file is in the way"):
            output_dir(tmp_path / "f" / "sub", "--out-dir", create=create)


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux /proc")
def test_output_dir_under_proc_is_refused_before_the_run() -> None:
    # os.access says "writable" to root here; the probe finds out before a training run, not at its end
    for create in (False, True):
        with pytest.raises(ConfigError, match="cannot create the folder"):
            output_dir("/proc/reradar-test/weights", "--out-dir", create=create)


def test_output_file_names_what_is_wrong(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="is a folder"):
        output_file(tmp_path, suffixes=(".h5",))
    with pytest.raises(ConfigError, match=r"must end in \.h5"):
        output_file(tmp_path / "map.txt", suffixes=(".h5",))
    assert output_file(tmp_path / "new" / "map.h5", suffixes=(".h5",)).parent.is_dir()
