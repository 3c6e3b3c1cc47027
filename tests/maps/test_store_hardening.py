"""Map store hardening (QA session 21): every malformed map - descriptor widths, damaged HDF5, declared-huge
datasets, bad timestamps / descriptors / attributes - is a ``MapFormatError`` saying what is wrong, raised before
the data is read where the header tells; maps the builder writes still open."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tracemalloc
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np
import pytest

from maps.store import (
    MAX_KEYPOINTS_PER_KEYFRAME,
    UNKNOWN_RADAR_PRESET,
    MapMetadata,
    open_map,
    probe_map,
    read_metadata,
    write_map,
)
from reradar_core.errors import MapFormatError
from reradar_core.features import ScanFeatures

D, C, N, K = 16, 8, 3, 12

Edit = Callable[[h5py.File], object]


def _meta(**kw: object) -> MapMetadata:
    base = dict(model_id="test-model", weights_sha256="a" * 64, radar_preset="boreas", cartesian_width_px=201,
                cartesian_resolution_m=0.64, descriptor_dim=D, local_descriptor_dim=C, name="t")
    base.update(kw)
    return MapMetadata(**base)  # type: ignore[arg-type]


def _features(seed: int = 0) -> list[ScanFeatures]:
    rng = np.random.default_rng(seed)
    out = []
    for i in range(N):
        g = rng.normal(size=D)
        loc = rng.normal(size=(K, C))
        loc /= np.linalg.norm(loc, axis=1, keepdims=True)
        out.append(ScanFeatures(g / np.linalg.norm(g), rng.uniform(-80, 80, (K, 2)), loc, 1_000_000 + i * 250_000))
    return out


def _map(tmp_path: Path, name: str, edit: Edit | None = None, **meta: object) -> Path:
    path = write_map(tmp_path / f"{name}.h5", _meta(**meta), _features(), np.zeros((N, 3)))
    if edit is not None:
        with h5py.File(path, "r+") as f:
            edit(f)
    return path


def _replace(name: str, data: object = None, **kw: object) -> Edit:
    def edit(f: h5py.File) -> None:
        del f[name]
        f.create_dataset(name, data=data, **kw)
    return edit


def _attr(name: str, value: object) -> Edit:
    return lambda f: f.attrs.__setitem__(name, value)


def _open_all(path: Path) -> None:
    """Open the map and read every keyframe (what registration does through the shared arrays file)."""
    with open_map(path) as m:
        for i in range(len(m)):
            m.read_keyframe(i)


def _local_width(width: int) -> Edit:
    def edit(f: h5py.File) -> None:
        for name in f["keyframes"]:
            del f["keyframes"][name]["local_descriptors"]
            f["keyframes"][name].create_dataset("local_descriptors", data=np.full((K, width), 0.5, np.float16))
    return edit


def _keyframe_entry_is_a_dataset(f: h5py.File) -> None:
    del f["keyframes/000001"]
    f["keyframes"].create_dataset("000001", data=[1])


def _unwritten_keyframe(rows: int) -> Edit:
    """Keyframe 1's datasets declared with ``rows`` keypoints, chunked and compressed, nothing written."""
    def edit(f: h5py.File) -> None:
        grp = f["keyframes/000001"]
        del grp["keypoints_xy_m"], grp["local_descriptors"]
        grp.create_dataset("keypoints_xy_m", shape=(rows, 2), dtype=np.float32, chunks=(1024, 2), compression="gzip")
        grp.create_dataset("local_descriptors", shape=(rows, C), dtype=np.float16, chunks=(1024, C),
                           compression="gzip")
    return edit


def _huge_local_values(f: h5py.File) -> None:  # float64 beyond float16: inf once read
    del f["keyframes/000000/local_descriptors"]
    f["keyframes/000000"].create_dataset("local_descriptors", data=np.full((K, C), 1e6))


BAD_MAPS: dict[str, tuple[Edit, str]] = {
    # F1: local descriptors of another width than the map's local_descriptor_dim
    "local-width": (_local_width(4), r"'/keyframes/000000/local_descriptors' has shape \(12, 4\), expected \(12, 8\)"),
    # F2a: a keyframe entry that is a dataset, not a group
    "keyframe-dataset": (_keyframe_entry_is_a_dataset, "keyframe 1: '/keyframes/000001' is not a group"),
    "too-many-keypoints": (_unwritten_keyframe(MAX_KEYPOINTS_PER_KEYFRAME + 1),
                           f"keyframe 1 has {MAX_KEYPOINTS_PER_KEYFRAME + 1} keypoints; at most"),
    "unwritten-keyframe": (_unwritten_keyframe(60_000), r"declares 480000 bytes of data but the file stores 0"),
    "int-keypoints": (_replace("keyframes/000002/keypoints_xy_m", np.zeros((K, 2), np.int32)),
                      "keypoints_xy_m' has dtype int32, expected float32"),
    "local-overflow": (_huge_local_values, "keyframe 0: local_descriptors contain NaN/inf"),
    # F4: declared shapes checked before anything is read
    "group-count": (lambda f: f["keyframes"].create_group("000003"), "4 keyframe groups for num_keyframes = 3"),
    "poses-shape": (_replace("poses", np.zeros((N, 2))), r"'/poses' has shape \(3, 2\), expected \(3, 3\)"),
    "descriptor-shape": (_replace("global_descriptors", np.full((N, D + 1), 0.25, np.float32)),
                         r"'/global_descriptors' has shape \(3, 17\), expected \(3, 16\)"),
    # F5: timestamps
    "timestamps-nan": (_replace("timestamps_us", np.full(N, np.nan)),
                       "'/timestamps_us' has dtype float64, expected int64"),
    "timestamps-float": (_replace("timestamps_us", np.arange(N) + 1e15), "dtype float64, expected int64"),
    "timestamps-equal": (_replace("timestamps_us", np.full(N, 1_600_000_000_000_000, np.int64)),
                         "timestamp 1600000000000000 us appears more than once"),
    "timestamps-duplicate": (_replace("timestamps_us", np.array([5, 7, 5], np.int64)), "timestamp 5 us appears"),
    "timestamps-negative": (_replace("timestamps_us", np.array([-1, 0, 1], np.int64)), "must be non-negative"),
    "timestamps-uint64": (_replace("timestamps_us", np.array([1, 2, 2**63], np.uint64)), "within int64"),
    # F5: global descriptors
    "descriptors-huge": (_replace("global_descriptors", np.full((N, D), 1e30, np.float32)),
                         "global descriptor of keyframe 0 has L2 norm 4e\\+30; global descriptors must be L2"),
    "descriptors-zero": (_replace("global_descriptors", np.zeros((N, D), np.float32)), "has L2 norm 0;"),
    "descriptors-int8": (_replace("global_descriptors", np.ones((N, D), np.int8)),
                         "'/global_descriptors' has dtype int8, expected float32"),
    "descriptors-nan": (_replace("global_descriptors", np.full((N, D), np.nan, np.float32)), "contain NaN/inf"),
    "descriptors-overflow": (_replace("global_descriptors", np.full((N, D), 1e300)), "contain NaN/inf"),
    "poses-nan": (_replace("poses", np.full((N, 3), np.nan)), "/poses contain NaN/inf"),
    # F8: attributes
    "preset-bogus": (_attr("radar_preset", "bogus"), "radar_preset 'bogus' is not a known radar preset"),
    "descriptor-dim-huge": (_attr("descriptor_dim", 10**9), "descriptor_dim = 1000000000 must be between 1 and"),
    "local-dim-zero": (_attr("local_descriptor_dim", 0), "local_descriptor_dim = 0 must be between 1 and"),
    "keyframes-negative": (_attr("num_keyframes", -1), "num_keyframes = -1 must be >= 0"),
    "attribute-array": (_attr("num_keyframes", np.arange(1000)), r"'num_keyframes' must be a single value, found "
                                                                 r"shape \(1000,\)"),
    "attribute-text": (_attr("descriptor_dim", "16"), "'descriptor_dim' must be an integer, found '16'"),
    "attribute-empty": (_attr("descriptor_dim", h5py.Empty("i8")), "'descriptor_dim' must be a single value"),
    "resolution-negative": (_attr("cartesian_resolution_m", -0.5), "must be a positive number, found"),
}


@pytest.mark.parametrize("case", sorted(BAD_MAPS))
def test_malformed_maps_are_refused_with_a_reason(tmp_path: Path, case: str) -> None:
    edit, match = BAD_MAPS[case]
    path = _map(tmp_path, case, edit)
    with pytest.raises(MapFormatError, match=match) as info:
        _open_all(path)
    message = str(info.value)
    assert message.startswith(f"{path}: ") and message.count(str(tmp_path)) == 1  # only the map's own name


def test_maps_of_the_builder_still_open(tmp_path: Path) -> None:
    """Valid variations: the preset recorded as the builder writes it without one (``unknown``) or in upper case,
    keyframes in another order than time, keyframes without keypoints, compressed datasets."""
    _open_all(_map(tmp_path, "unknown", radar_preset=UNKNOWN_RADAR_PRESET))
    _open_all(_map(tmp_path, "upper", radar_preset="Boreas"))
    _open_all(_map(tmp_path, "reversed", _replace("timestamps_us", np.array([9, 5, 1], np.int64))))

    def compressed(f: h5py.File) -> None:
        for name in ("keypoints_xy_m", "local_descriptors"):
            data = f[f"keyframes/000000/{name}"][()]
            del f[f"keyframes/000000/{name}"]
            f["keyframes/000000"].create_dataset(name, data=data, chunks=True, compression="gzip")

    _open_all(_map(tmp_path, "compressed", compressed))
    rng = np.random.default_rng(1)
    feats = [ScanFeatures(f.global_descriptor, np.zeros((0, 2)), np.zeros((0, C)), f.timestamp_us)
             for f in _features()]
    path = write_map(tmp_path / "empty.h5", _meta(), feats, rng.uniform(-5, 5, (N, 3)))
    with open_map(path) as m:
        assert m.read_keyframe(1).local_descriptors.shape == (0, C)


def test_declared_huge_timestamps_are_refused_without_reading_them(tmp_path: Path) -> None:
    """QA F4: a small file declaring /timestamps_us of 200 million int64 (chunked, gzip, nothing written) took
    1.5 GB to open; it is now refused from its header: nothing near that size is allocated."""
    def bomb(f: h5py.File) -> None:
        del f["timestamps_us"]
        f.create_dataset("timestamps_us", shape=(200_000_000,), dtype=np.int64, chunks=(1 << 20,), compression="gzip")

    path = _map(tmp_path, "bomb", bomb)
    assert path.stat().st_size < 1 << 20
    tracemalloc.start()
    try:
        with pytest.raises(MapFormatError, match=r"'/timestamps_us' has shape \(200000000,\), expected \(3,\)"):
            open_map(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 50 << 20  # reading it would allocate 1.6 GB (numpy reports its buffers to tracemalloc)


def test_declared_huge_keyframe_is_refused_without_reading_it(tmp_path: Path) -> None:
    path = _map(tmp_path, "kbomb", _unwritten_keyframe(MAX_KEYPOINTS_PER_KEYFRAME))
    with open_map(path) as m:
        m.read_keyframe(0)
        tracemalloc.start()
        try:
            with pytest.raises(MapFormatError, match="datasets must be written in full"):
                m.read_keyframe(1)
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
    assert peak < 256 << 10


#: Run in a child process by ``test_damaged_hdf5_is_a_map_format_error``: damaged variants of the map at argv[1]
#: (seeded by argv[2]), each opened and read through in a fork of its own (the HDF5 library crashes or spins on
#: some: uploads are read in a child process for that, ``probe_map``); prints the count of each outcome.
_DAMAGE_LOOP = """
import json, os, random, signal, sys, time
from pathlib import Path
from maps.store import open_map, read_metadata
from reradar_core.errors import MapFormatError
data = Path(sys.argv[1]).read_bytes()
rnd = random.Random(int(sys.argv[2]))
path = Path(sys.argv[1]).with_name("damaged.h5")
result = {"opened": 0, "refused": 0, "crashed": 0, "hung": 0, "other": []}
for _ in range(int(sys.argv[3])):
    b = bytearray(data)
    kind = rnd.random()
    if kind < 0.45:  # a few random bytes
        for _ in range(rnd.randint(1, 8)):
            b[rnd.randrange(len(b))] = rnd.randrange(256)
    elif kind < 0.9:  # a zeroed range
        start = rnd.randrange(len(b))
        size = rnd.randint(1, 512)
        b[start:start + size] = bytes(len(b[start:start + size]))
    else:  # truncated
        b = b[:rnd.randrange(len(b))]
    path.write_bytes(bytes(b))
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:
        os.close(r)
        code = 0
        try:
            read_metadata(path)
            with open_map(path) as m:
                for i in range(len(m)):
                    m.read_keyframe(i)
        except MapFormatError as exc:
            code = 3
            if str(exc).count(str(path.parent)) != 1:
                os.write(w, ("server folder in: " + str(exc))[:300].encode())
        except BaseException as exc:
            code = 4
            os.write(w, (type(exc).__name__ + ": " + str(exc))[:300].encode())
        os._exit(code)
    os.close(w)
    deadline = time.monotonic() + 20
    while (status := os.waitpid(pid, os.WNOHANG))[0] == 0 and time.monotonic() < deadline:
        time.sleep(0.001)
    if status[0] == 0:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        result["hung"] += 1
    elif os.WIFSIGNALED(status[1]):
        result["crashed"] += 1
    else:
        result[{0: "opened", 3: "refused"}.get(os.WEXITSTATUS(status[1]), "refused")] += 1
    message = os.read(r, 400).decode(errors="replace")
    os.close(r)
    if message:
        result["other"].append(message)
print(json.dumps(result))
"""


def test_damaged_hdf5_is_a_map_format_error(tmp_path: Path) -> None:
    """QA F2b: a valid superblock with the rest of the file zeroed failed with h5py's RuntimeError ("Link
    visitation failed"); every damaged variant of a small map is now refused as a MapFormatError (or opens, where
    the damage hits nothing that is read), with h5py's reasons carrying no server folder - or crashes / hangs the
    HDF5 library itself, which ``probe_map`` turns into a refusal (``test_probe_...``)."""
    data = _map(tmp_path, "base").read_bytes()
    zeroed = tmp_path / "zeroed.h5"
    zeroed.write_bytes(data[:512] + bytes(len(data) - 512))
    for reader in (open_map, read_metadata):
        with pytest.raises(MapFormatError, match="corrupt map file|not a readable HDF5") as info:
            reader(zeroed)
        assert str(info.value).count(str(tmp_path)) == 1
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p))
    done = subprocess.run([sys.executable, "-c", _DAMAGE_LOOP, str(tmp_path / "base.h5"), "21", "100"],
                          capture_output=True, env=env, timeout=900, check=False)
    assert done.returncode == 0, done.stderr.decode()[-2000:]
    result = json.loads(done.stdout)
    assert result["other"] == [], result["other"]  # no exception but MapFormatError, no server folder
    assert result["refused"] > 30 and sum(result[k] for k in ("opened", "refused", "crashed", "hung")) == 100


def test_damaged_global_heap_is_refused_before_hdf5_reads_it(tmp_path: Path) -> None:
    """A global heap collection (the text attributes' storage) whose first object has index 0 and size 0 makes
    the HDF5 library loop forever at 100 % CPU holding h5py's lock; it is refused before h5py opens the file. (Read
    in a child process with a time limit, so that a regression fails instead of hanging.)"""
    data = _map(tmp_path, "base").read_bytes()
    heap = data.index(b"GCOL")
    path = tmp_path / "heap.h5"
    path.write_bytes(data[:heap + 16] + bytes(16) + data[heap + 32:])
    with pytest.raises(MapFormatError, match=f"global heap at byte {heap} is damaged"):
        probe_map(path, timeout_s=120)
    overrun = bytearray(data)
    overrun[heap + 8:heap + 16] = (1 << 40).to_bytes(8, "little")  # the collection's size: beyond the file
    path.write_bytes(bytes(overrun))
    with pytest.raises(MapFormatError, match=f"global heap at byte {heap} overruns the file"):
        probe_map(path, timeout_s=120)  # refused before the child starts


def test_probe_reads_untrusted_maps_in_a_child_process(tmp_path: Path) -> None:
    """``probe_map`` (uploads): a valid map passes, a refusal carries the same message as in-process, and a file
    that crashes the HDF5 library (an invalid variable-length string type on an attribute: a segfault with HDF5
    2.0) is a MapFormatError of the child, this process unharmed."""
    probe_map(_map(tmp_path, "good"))
    bad = _map(tmp_path, "bogus", _attr("radar_preset", "bogus"))
    with pytest.raises(MapFormatError, match=f"^{bad}: radar_preset 'bogus' is not a known radar preset"):
        probe_map(bad)
    data = bytearray(_map(tmp_path, "base").read_bytes())
    vlen = data.index(b"name\0\0\0\0\x19\x01") + 9  # the "name" attribute's datatype: variable-length string
    data[vlen] = 0x74  # an invalid variable-length kind
    crash = tmp_path / "crash.h5"
    crash.write_bytes(bytes(data))
    with pytest.raises(MapFormatError, match="corrupt map file"):
        probe_map(crash)
