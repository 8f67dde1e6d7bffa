"""A size-limited filesystem that tests mount (tmpfs, as root) to fill a disk for real."""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest


@contextlib.contextmanager
def small_filesystem(path: Path, size_mb: int) -> Iterator[Path]:
    """Mount a ``size_mb`` tmpfs at ``path`` for the block; skips only where mounting is impossible (never in CI)."""
    path.mkdir(parents=True, exist_ok=True)
    mounted = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size_mb}m,mode=0755", "tmpfs", str(path)], capture_output=True, text=True
    )
    if mounted.returncode != 0:
        why = f"cannot mount a {size_mb} MB tmpfs at {path}: {mounted.stderr.strip() or 'mount failed'}"
        if os.environ.get("CI"):
            pytest.fail(why + " (CI runs as root and must test a full disk)")
        pytest.skip(why)
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], capture_output=True)


def fill(folder: Path, leave_bytes: int, name: str = "filler.bin") -> Path:
    """Write a file that leaves about ``leave_bytes`` free on ``folder``'s filesystem."""
    target = folder / name
    size = max(shutil.disk_usage(folder).free - leave_bytes, 0)
    with open(target, "wb") as fh:
        chunk = b"\0" * (1 << 20)
        try:
            while size > 0:
                n = fh.write(chunk[: min(size, len(chunk))])
                size -= n
            fh.flush()
            os.fsync(fh.fileno())
        except OSError as exc:  # another writer took the last bytes first: the disk is full, as asked
            if exc.errno != errno.ENOSPC:
                raise
    return target


class FailingFilesystem:
    """An ext4 image mounted with ``errors=remount-ro`` at ``path``: :meth:`turn_read_only` makes the kernel turn it
    read-only under every open file, as a disk error would; :meth:`repair` does what an operator then does (unmount,
    ``e2fsck``, mount again at the same place)."""

    def __init__(self, path: Path, image: Path) -> None:
        self.path, self.image = path, image
        self.devices: list[str] = []  # loop devices set up by :meth:`repair` (detached at the end)

    def _device(self) -> str:
        source = subprocess.run(["findmnt", "-n", "-o", "SOURCE", str(self.path)], capture_output=True, text=True)
        return Path(source.stdout.strip().splitlines()[-1]).name

    def turn_read_only(self) -> None:
        """An ext4 error: the kernel turns the filesystem read-only at once (EROFS for every write). What was written
        before is synced first (ext4 commits every few seconds; the test asks for an error after that)."""
        os.sync()
        Path(f"/sys/fs/ext4/{self._device()}/trigger_fs_error").write_text("orbitct test: a disk error\n")

    def repair(self) -> None:
        """Unmount (lazily: the service still holds files), check and mount again: writable, the same data."""
        subprocess.run(["umount", "-l", str(self.path)], check=True)
        subprocess.run(["e2fsck", "-fy", str(self.image)], capture_output=True)  # exit 1: it fixed something
        # a loop device of its own: `mount -o loop` would reuse the old one, whose filesystem stays read-only
        device = subprocess.run(
            ["losetup", "--find", "--show", str(self.image)], capture_output=True, text=True, check=True
        ).stdout.strip()
        subprocess.run(["mount", "-o", "errors=remount-ro", device, str(self.path)], check=True)
        self.devices.append(device)


@contextlib.contextmanager
def failing_filesystem(path: Path, size_mb: int) -> Iterator[FailingFilesystem]:
    """Mount a ``size_mb`` ext4 image at ``path`` that the test can turn read-only; skips only where loop devices are
    impossible (never in CI)."""
    image = path.with_name(path.name + ".ext4")
    path.mkdir(parents=True, exist_ok=True)
    with open(image, "wb") as fh:
        fh.truncate(size_mb << 20)
    made = subprocess.run(["mkfs.ext4", "-q", "-F", str(image)], capture_output=True, text=True)
    mounted = (
        made.returncode == 0
        and subprocess.run(
            ["mount", "-o", "loop,errors=remount-ro", str(image), str(path)], capture_output=True, text=True
        ).returncode
        == 0
    )
    if not mounted:
        why = f"cannot make and loop-mount an ext4 image at {path}: {made.stderr.strip() or 'mount failed'}"
        if os.environ.get("CI"):
            pytest.fail(why + " (CI runs as root and must test a read-only filesystem)")
        pytest.skip(why)
    fs = FailingFilesystem(path, image)
    try:
        yield fs
    finally:
        subprocess.run(["umount", "-l", str(path)], capture_output=True)
        for device in fs.devices:
            subprocess.run(["losetup", "-d", device], capture_output=True)
        image.unlink(missing_ok=True)
