"""Single frames of a scan read from any thread: straight from the file where HDF5 stores them as they are, so
that reading does not hold Python's lock while other threads search or reconstruct."""

from __future__ import annotations

import os
import threading
from typing import Any

import h5py
import numpy as np
from numpy.typing import NDArray


class FrameReader:
    """Reads frame ``i`` of an ``(N, rows, cols)`` dataset into a new array, from any thread. Frames stored one per
    chunk, unfiltered, in native byte order, in a file on disk opened read-only (the one HDF5 has open, not another
    put in its place since), are read with ``os.preadv`` at their chunk's offset (the GIL is released while the
    kernel copies them); any other frame (compressed, not yet written, a driver without a file) through h5py,
    giving what h5py gives."""

    def __init__(self, data: h5py.Dataset) -> None:
        self.data = data
        self.shape = tuple(data.shape[1:])
        self.dtype = data.dtype
        self._lock = threading.Lock()  # h5py calls, one at a time
        self._fd: int | None = None
        self._size = 0
        nbytes = int(np.prod(self.shape)) * self.dtype.itemsize
        if (
            hasattr(os, "preadv")  # not on Windows
            and data.ndim == 3
            and data.chunks == (1, *self.shape)
            and data.file.mode == "r"
            and data.file.driver == "sec2"
            and self.dtype.isnative
            and data.id.get_create_plist().get_nfilters() == 0
        ):
            fd = os.open(data.file.filename, os.O_RDONLY)
            mine, hdf5s = os.fstat(fd), os.fstat(data.file.id.get_vfd_handle())
            if (mine.st_dev, mine.st_ino) == (hdf5s.st_dev, hdf5s.st_ino):  # not a file put in its place since
                self._fd, self._size = fd, mine.st_size
            else:
                os.close(fd)
        self._nbytes = nbytes

    @property
    def direct(self) -> bool:
        """Whether frames are read straight from the file."""
        return self._fd is not None

    def read(self, index: int) -> NDArray[Any]:
        """Frame ``index`` as a new ``(rows, cols)`` array."""
        out = np.empty(self.shape, self.dtype)
        if self._fd is not None:
            with self._lock:
                info = self.data.id.get_chunk_info_by_coord((int(index), 0, 0))
            offset = info.byte_offset
            if (
                offset is not None
                and info.size == self._nbytes
                and info.filter_mask == 0
                and offset + self._nbytes <= self._size
                and os.preadv(self._fd, [out.data.cast("B")], offset) == self._nbytes
            ):
                return out
        with self._lock:
            self.data.read_direct(out, np.s_[int(index)])
        return out

    def close(self) -> None:
        """Close the file descriptor (the dataset stays open)."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> FrameReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
