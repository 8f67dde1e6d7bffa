"""A scan file exported as NXtomo and read back with the nxtomo library: frames, image keys, angles, distances, the
per-frame transformations and the full per-view geometry."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest
from nxtomo import NXtomo

from orbitct.scanfile import ScanFile, ScanFileError
from orbitct.scanfile.nxtomo import ENTRY, export_nxtomo
from orbitct.simulator import simulate_scan


def test_a_simulated_scan_reads_back_through_nxtomo(tmp_path: Path) -> None:
    scan = simulate_scan(
        "A", out=tmp_path / "s.h5", n_frames=12, detector_px=48, n_dark=1, n_flat=2, seed=2, errors="bench"
    ).path
    out = export_nxtomo(scan, tmp_path / "s.nx")
    nx = NXtomo().load(str(out), data_path=ENTRY)
    with ScanFile(scan) as sf:
        keys, frames, axes = sf.image_key, np.asarray(sf.frames[: sf.n_frames]), sf.axes("commanded")
        nominal = sf.geometry("nominal")
        pitch = sf.panel.pitch_mm
    assert [k.value for k in nx.instrument.detector.image_key_control] == keys.astype(int).tolist()
    assert np.allclose(nx.sample.rotation_angle.to("degree").magnitude, axes["orbit.rotation"], equal_nan=True)
    assert np.isfinite(axes["orbit.rotation"][keys == 0]).all()
    assert nx.instrument.detector.x_pixel_size.to("mm").magnitude == pytest.approx(pitch[0])
    proj = keys == 0
    sod, sdd = np.median(nominal.sod()[proj]), np.median(nominal.sdd[proj])
    assert nx.instrument.source.distance.to("mm").magnitude == pytest.approx(sod)
    assert nx.instrument.detector.distance.to("mm").magnitude == pytest.approx(sdd - sod)
    with h5py.File(out) as f:
        assert np.array_equal(f[f"{ENTRY}/instrument/detector/data"][()], frames)
        t = f[f"{ENTRY}/sample/transformations"]
        assert f[f"{ENTRY}/sample"].attrs["depends_on"] == "transformations/rotation"
        assert t["rotation"].attrs["depends_on"] == "tilt" and t["tilt"].attrs["depends_on"] == "."
        assert np.allclose(t["tilt"][()], axes["orbit.tilt"], equal_nan=True) and list(t["tilt"].attrs["vector"]) == [
            1.0,
            0.0,
            0.0,
        ]
        vectors = f[f"{ENTRY}/orbitct/nominal_vectors"][()]
        assert np.allclose(vectors, nominal.vectors, equal_nan=True)
        assert "truth_vectors" in f[f"{ENTRY}/orbitct"]  # a simulated file has its true geometry too


def test_export_refuses_to_overwrite_and_names_what_is_wrong(tmp_path: Path) -> None:
    scan = simulate_scan("A", out=tmp_path / "s.h5", n_frames=4, detector_px=32, n_dark=1, n_flat=1, seed=1).path
    out = export_nxtomo(scan, tmp_path / "s.nx")
    with pytest.raises(ScanFileError, match="exists"):
        export_nxtomo(scan, out)
    assert export_nxtomo(scan, out, overwrite=True) == out
    with pytest.raises(ScanFileError, match="no such file"):
        export_nxtomo(tmp_path / "missing.h5", tmp_path / "m.nx")
