"""Folder-watch adapter: frames that a vendor tool writes to disk (TIFF, raw with and without header)."""

from __future__ import annotations

import asyncio
from pathlib import Path

import numpy as np
import pytest
import tifffile

from devices.errors import (
    DeviceTimeoutError,
    NotConnectedError,
    ProtocolError,
    UriError,
)
from devices.folder_detector import FolderWatchDetector, write_raw_frame

pytestmark = pytest.mark.timeout(60)


def frame(value: int, shape: tuple[int, int] = (16, 24)) -> np.ndarray:
    return np.full(shape, value, np.uint16) + np.arange(shape[1], dtype=np.uint16)


async def write_later(delay_s: float, writer: object, *args: object) -> None:
    await asyncio.sleep(delay_s)
    writer(*args)  # type: ignore[operator]


def test_tiff_frames_in_order_and_old_files_ignored(tmp_path: Path) -> None:
    tifffile.imwrite(tmp_path / "old.tif", frame(1))  # before arming: not a frame of this session

    async def main() -> None:
        det = FolderWatchDetector("panel", f"folder://{tmp_path}?pattern=*.tif", timeout_s=2.0, poll_s=0.01)
        await det.connect()
        writer = asyncio.ensure_future(write_later(0.05, tifffile.imwrite, tmp_path / "img_0001.tif", frame(100)))
        first = await det.trigger()
        await writer
        assert first.number == 1 and first.kind == "projection" and first.meta["file"].endswith("img_0001.tif")
        np.testing.assert_array_equal(first.data, frame(100))
        assert det.shape == (16, 24)
        tifffile.imwrite(tmp_path / "img_0002.tif", frame(200))
        tifffile.imwrite(tmp_path / "notes.txt.tif.bak", frame(0))  # not matching the pattern
        darks = await det.acquire_dark(1)
        assert darks[0].kind == "dark" and darks[0].number == 2 and int(darks[0].data[0, 0]) == 200
        assert (await det.read())["waiting"] == 0

    asyncio.run(main())


def test_raw_with_header_and_without(tmp_path: Path) -> None:
    async def main() -> None:
        det = FolderWatchDetector("panel", f"folder://{tmp_path}?pattern=*.raw", timeout_s=1.0, poll_s=0.01)
        await det.connect()
        write_raw_frame(tmp_path / "a.raw", frame(7, (8, 8)), number=41, exposure_ms=12.5)
        got = await det.read_frame()
        assert got.meta["file_frame_number"] == 41 and got.meta["exposure_ms"] == 12.5
        np.testing.assert_array_equal(got.data, frame(7, (8, 8)))

        bare = FolderWatchDetector("panel", f"folder://{tmp_path}?pattern=*.bin&rows=4&cols=6&header_bytes=16")
        await bare.connect()
        (tmp_path / "b.bin").write_bytes(b"\0" * 16 + frame(3, (4, 6)).astype("<u2").tobytes())
        np.testing.assert_array_equal((await bare.read_frame()).data, frame(3, (4, 6)))

        (tmp_path / "c.bin").write_bytes(b"\0" * 10)
        with pytest.raises(ProtocolError, match="expected 16 header"):
            await bare.read_frame()

        write_raw_frame(tmp_path / "d.raw", frame(1, (9, 9)), number=42)
        with pytest.raises(ProtocolError, match="expected"):
            await det.read_frame()  # shape differs from the first frame

    asyncio.run(main())


def test_missing_frame_times_out(tmp_path: Path) -> None:
    async def main() -> None:
        det = FolderWatchDetector("panel", f"folder://{tmp_path}", timeout_s=0.1, poll_s=0.01)
        await det.connect()
        with pytest.raises(DeviceTimeoutError, match="frame 1 missing"):
            await det.read_frame()

    asyncio.run(main())


def test_bad_folder_and_options(tmp_path: Path) -> None:
    async def main() -> None:
        with pytest.raises(NotConnectedError, match="does not exist"):
            await FolderWatchDetector("panel", f"folder://{tmp_path}/nope").connect()

    asyncio.run(main())
    with pytest.raises(UriError, match="allowed"):
        FolderWatchDetector("panel", f"folder://{tmp_path}?colour=red")
    with pytest.raises(UriError, match="folder:///"):
        FolderWatchDetector("panel", "tcp://127.0.0.1:5")
    (tmp_path / "x.raw").write_bytes(b"1234")
    with pytest.raises(ProtocolError, match="rows="):
        from devices.folder_detector import read_frame_file

        read_frame_file(tmp_path / "x.raw")


def test_detector_factory_name_gives_folder_watch(tmp_path: Path) -> None:
    from devices.factory import open_device

    async def main() -> None:
        det = await open_device("detector", "panel", f"folder://{tmp_path}?pattern=*.tif", pitch_mm=0.278)
        assert isinstance(det, FolderWatchDetector)
        await det.set_trigger("xray")
        with pytest.raises(Exception, match="vendor software"):
            await det.set_binning(2)
        tifffile.imwrite(tmp_path / "f.tif", frame(5))
        await det.read_frame(timeout_s=2.0)
        assert det.geometry.pitch_col == 0.278 and det.geometry.shape == (16, 24)
        await det.close()

    asyncio.run(main())
