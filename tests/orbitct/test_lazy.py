"""The walls' heavy parts load on first use: their options and errors import without numba or SciPy."""

from __future__ import annotations

import subprocess
import sys

import pytest


def test_the_options_of_calibration_and_reconstruction_import_without_the_kernels() -> None:
    code = (
        "import sys, calib, recon, calib.options, recon.options; "
        "print(sorted(m for m in ('numba', 'scipy', 'calib.pipeline', 'recon.pipeline') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_a_lazy_name_is_the_one_in_its_module_and_an_unknown_name_is_refused() -> None:
    import calib
    import calib.pipeline
    import recon
    import recon.fdk
    import recon.operator
    import recon.pipeline

    assert calib.calibrate_scan is calib.pipeline.calibrate_scan
    assert recon.reconstruct_scan is recon.pipeline.reconstruct_scan
    # functions named as their modules stay the functions, whichever was imported first
    assert recon.fdk is sys.modules["recon.fdk"].fdk and recon.projector is recon.operator.projector
    assert "calibrate_scan" in vars(calib)  # found directly from now on
    with pytest.raises(AttributeError, match="module 'calib' has no attribute 'calibrate'"):
        calib.calibrate  # noqa: B018


def test_a_submodule_imported_first_does_not_hide_the_function_of_its_name() -> None:
    code = (
        "import recon.pipeline, recon, recon.fdk, recon.operator; print(callable(recon.fdk), callable(recon.projector))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["True", "True"]
