"""Frames read from any thread (:class:`orbitct.scanfile.FrameReader`): straight from the file where the scan stores
them as they are, through h5py otherwise, the same pixels either way."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import h5py
import numpy as np

from orbitct.scanfile import FrameReader, ScanFile, write_linked_scan
from tests.orbitct.test_scanfile import _write


def test_a_scans_frames_are_read_straight_from_the_file_from_many_threads(tmp_path: Path) -> None:
    scan = tmp_path / "scan.h5"
    _write(scan, n_proj=12)
    with ScanFile(scan) as sf:
        want = sf.frames[...]
        with FrameReader(sf.frames) as frames, ThreadPoolExecutor(4) as pool:
            assert frames.direct
            got = list(pool.map(frames.read, [i % len(want) for i in range(4 * len(want))]))
    for i, frame in enumerate(got):
        assert frame.dtype == want.dtype and frame.flags.c_contiguous
        np.testing.assert_array_equal(frame, want[i % len(want)])


def test_a_linked_scan_reads_the_frames_of_the_scan_it_names(tmp_path: Path) -> None:
    scan = tmp_path / "scan.h5"
    _write(scan)
    linked = write_linked_scan(scan, tmp_path / "out.h5")
    with ScanFile(linked) as sf, FrameReader(sf.frames) as frames:
        assert frames.direct
        np.testing.assert_array_equal(np.stack([frames.read(i) for i in range(sf.n_frames)]), sf.frames[...])


def test_frames_stored_otherwise_come_through_h5py(tmp_path: Path) -> None:
    """Compressed frames, byte-swapped ones, several frames a chunk, a file open for writing: h5py reads them; a
    frame whose chunk was never written reads as h5py's fill value, straight or not."""
    rng = np.random.default_rng(1)
    data = rng.integers(0, 60000, (4, 6, 5)).astype(np.uint16)
    path = tmp_path / "frames.h5"
    with h5py.File(path, "w") as f:
        f.create_dataset("gzip", data=data, chunks=(1, 6, 5), compression="gzip")
        f.create_dataset("swapped", data=data.astype(">u2"), chunks=(1, 6, 5))
        f.create_dataset("two", data=data, chunks=(2, 6, 5))
        plain = f.create_dataset("plain", shape=data.shape, dtype=np.uint16, chunks=(1, 6, 5), fillvalue=7)
        plain[:2] = data[:2]  # frames 2 and 3 never written
    with h5py.File(path, "r") as f:
        for name in ("gzip", "swapped", "two"):
            with FrameReader(f[name]) as frames:
                assert not frames.direct, name
                np.testing.assert_array_equal(np.stack([frames.read(i) for i in range(4)]), data, err_msg=name)
        with FrameReader(f["plain"]) as frames:
            assert frames.direct
            np.testing.assert_array_equal(frames.read(1), data[1])
            np.testing.assert_array_equal(frames.read(3), np.full((6, 5), 7))
    with h5py.File(path, "r+") as f, FrameReader(f["plain"]) as frames:
        assert not frames.direct
        np.testing.assert_array_equal(frames.read(0), data[0])


def test_a_file_put_in_the_scans_place_is_not_read(tmp_path: Path) -> None:
    """The frames come from the file h5py opened, even when another file has taken its name since."""
    scan, other = tmp_path / "scan.h5", tmp_path / "other.h5"
    _write(scan)
    _write(other)
    with h5py.File(other, "r+") as f:
        f["frames/data"][...] = 1
    with ScanFile(scan) as sf:
        want = sf.frames[...]
        other.replace(scan)
        with FrameReader(sf.frames) as frames:
            assert not frames.direct
            np.testing.assert_array_equal(np.stack([frames.read(i) for i in range(len(want))]), want)
