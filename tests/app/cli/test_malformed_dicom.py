"""Hostile DICOM objects: ``orbitct import dicom`` refuses each in one sentence naming the file, with a non-zero exit,
within 2 s, never a traceback; the header is checked before a pixel is read."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pydicom
import pydicom.config
import pytest
from click.testing import CliRunner
from pydicom.encaps import encapsulate
from pydicom.uid import JPEG2000Lossless

from orbitct.scanfile.xa import write_xa_run
from orbitct_app.cli.main import cli
from tests.orbitct.test_xa import carm_scan  # noqa: F401 - the fixture: a C-arm scan of the twins

pytestmark = [pytest.mark.system, pytest.mark.timeout(180)]


def _set(**values: Any) -> Callable[[Any], None]:
    def edit(ds: Any) -> None:
        for name, value in values.items():
            setattr(ds, name, value)

    return edit


def _delete(name: str) -> Callable[[Any], None]:
    return lambda ds: delattr(ds, name)


def _cut_pixels(ds: Any) -> None:
    ds.PixelData = ds.PixelData[: len(ds.PixelData) // 3]


def _rgb(ds: Any) -> None:
    ds.SamplesPerPixel, ds.PhotometricInterpretation, ds.PlanarConfiguration = 3, "RGB", 0


def _undecodable_jpeg2000(ds: Any) -> None:
    ds.file_meta.TransferSyntaxUID = JPEG2000Lossless
    ds.PixelData = encapsulate([b"\xff\x4f not a codestream" for _ in range(int(ds.NumberOfFrames))])


EDITS: dict[str, Callable[[Any], None]] = {
    "ct-image-class": _set(SOPClassUID="1.2.840.10008.5.1.4.1.1.2"),
    "mr-image-class": _set(SOPClassUID="1.2.840.10008.5.1.4.1.1.4", Modality="MR"),
    "modality-ct": _set(Modality="CT"),
    "a-billion-frames": _set(NumberOfFrames=1_000_000_000),
    "zero-frames": _set(NumberOfFrames=0),
    "rows-zero": _set(Rows=0),
    "huge-panel": _set(Rows=60000, Columns=60000),
    "pixels-cut-short": _cut_pixels,
    "rgb-pixels": _rgb,
    "palette-colour": _set(PhotometricInterpretation="PALETTE COLOR"),
    "bits-12-allocated": _set(BitsAllocated=12),
    "pixel-spacing-nan": _set(ImagerPixelSpacing=["nan", "0.5"]),
    "pixel-spacing-negative": _set(ImagerPixelSpacing=[-0.5, 0.5]),
    "pixel-spacing-one-value": _set(ImagerPixelSpacing=[0.5]),
    "distance-nan": _set(DistanceSourceToDetector="nan"),
    "detector-inside-source": _set(DistanceSourceToDetector=500, DistanceSourceToPatient=800),
    "angle-nan": _set(PositionerPrimaryAngle="nan"),
    "angle-text": lambda ds: ds.add_new(ds.data_element("PositionerPrimaryAngle").tag, "LO", "LAO"),
    "increments-short": lambda ds: setattr(
        ds, "PositionerPrimaryAngleIncrement", list(ds.PositionerPrimaryAngleIncrement)[:-3]
    ),
    "increments-infinite": lambda ds: setattr(
        ds, "PositionerSecondaryAngleIncrement", ["inf"] * int(ds.NumberOfFrames)
    ),
    "log-pixels": _set(PixelIntensityRelationship="LOG"),
    "no-pixel-data": _delete("PixelData"),
    "jpeg2000-undecodable": _undecodable_jpeg2000,
}


def _write(valid: Path, folder: Path, name: str, edit: Callable[[Any], None]) -> Path:
    ds = pydicom.dcmread(valid)
    with pydicom.config.disable_value_validation():  # other writers' values, as they wrote them
        edit(ds)
        path = folder / f"{name}.dcm"
        ds.save_as(path, enforce_file_format=False)
    return path


def test_every_malformed_dicom_object_is_refused_in_one_sentence(carm_scan: Path, tmp_path: Path) -> None:  # noqa: F811
    valid = write_xa_run(carm_scan, tmp_path / "valid.dcm")
    r = CliRunner().invoke(cli, ["import", "dicom", str(valid), "--out", str(tmp_path / "valid.h5")])
    assert r.exit_code == 0, r.output
    files = [_write(valid, tmp_path, name, edit) for name, edit in EDITS.items()]
    data = valid.read_bytes()
    for name, content in {
        "truncated-half": data[: len(data) // 2],
        "header-only": data[:600],
        "empty": b"",
        "text": b"not a DICOM object\n" * 20,
    }.items():
        files.append(tmp_path / f"{name}.dcm")
        files[-1].write_bytes(content)
    assert len(files) >= 20
    for path in files:
        t = time.monotonic()
        r = CliRunner().invoke(cli, ["import", "dicom", str(path), "--out", str(tmp_path / f"{path.stem}.h5")])
        seconds = time.monotonic() - t
        crashed = r.exception is not None and not isinstance(r.exception, SystemExit)
        assert not crashed, (path.name, repr(r.exception))
        lines = [line for line in r.output.strip().splitlines() if line]
        assert r.exit_code != 0 and len(lines) == 1 and path.name in lines[0], (path.name, r.output)
        assert "Traceback" not in r.output and lines[0].startswith("error [") and seconds < 2.0, (
            path.name,
            seconds,
            r.output,
        )
        assert not (tmp_path / f"{path.stem}.h5").exists(), path.name  # nothing half-written


def test_the_class_of_a_ct_object_is_named(carm_scan: Path, tmp_path: Path) -> None:  # noqa: F811
    ct = _write(write_xa_run(carm_scan, tmp_path / "valid.dcm"), tmp_path, "ct", EDITS["ct-image-class"])
    r = CliRunner().invoke(cli, ["import", "dicom", str(ct), "--out", str(tmp_path / "x.h5")])
    assert "CT Image Storage" in r.output and "not an X-ray angiography or fluoroscopy run" in r.output, r.output


def test_a_billion_frames_are_refused_before_a_pixel_is_read(carm_scan: Path, tmp_path: Path) -> None:  # noqa: F811
    path = _write(write_xa_run(carm_scan, tmp_path / "valid.dcm"), tmp_path, "many", EDITS["a-billion-frames"])
    t = time.monotonic()
    r = CliRunner().invoke(cli, ["import", "dicom", str(path), "--out", str(tmp_path / "x.h5")])
    assert r.exit_code != 0 and time.monotonic() - t < 1.0 and "NumberOfFrames is" in r.output, r.output
