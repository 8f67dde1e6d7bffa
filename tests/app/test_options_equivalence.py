"""One options model per job: the command line, the REST API and Python accept and refuse the same options alike,
because all three are made from (or validated by) the same pydantic model."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Annotated, Any

import click
import pytest
from fastapi import FastAPI, Query
from pydantic import BaseModel, ValidationError

from calib.errors import OptionError
from calib.options import CalibrationOptions
from calib.options import checked_options as checked_calibration_options
from orbitct.dicom import DicomSeriesOptions
from orbitct_app.cli.calibrate import calibrate
from orbitct_app.cli.model_options import flag_of, model_from
from orbitct_app.cli.reconstruct import FLAGS, reconstruct
from orbitct_app.service.routers.calibrations import CalibrationRequest
from orbitct_app.service.routers.reconstructions import ReconstructionRequest
from recon import ReconError, ReconstructionOptions
from recon.pipeline import checked_options

SCAN_ID = "a1b2c3d4e5f60718"

# (options as Python takes them, whether they are acceptable)
CASES: list[tuple[dict[str, Any], bool]] = [
    ({}, True),
    ({"algorithm": "pwls", "iterations": 1}, True),
    ({"algorithm": "pwls", "iterations": 500, "subsets": 64, "momentum": True}, True),
    ({"iterations": 0}, False),
    ({"iterations": 501}, False),
    ({"subsets": 65}, False),
    ({"voxel_mm": 0.005}, False),
    ({"voxel_mm": 0.006}, True),
    ({"voxel_mm": 20.0}, True),
    ({"voxel_mm": 20.5}, False),
    ({"shape": [4, 4, 4]}, True),
    ({"shape": [3, 64, 64]}, False),
    ({"shape": [2048, 2048, 256]}, True),
    ({"shape": [2048, 2048, 257]}, False),  # more than 1024^3 voxels
    ({"shape": [64, 64]}, False),
    ({"beta": -0.1}, False),
    ({"beta": 0.0}, True),
    ({"neighbourhood": 2}, True),
    ({"neighbourhood": 3}, False),
    ({"geometry": "nominal", "fit": "fov"}, True),
    ({"geometry": "measured"}, False),
    ({"algorithm": "art"}, False),
    ({"window": "ram-lak", "mar": True, "mar_method": "threshold", "mar_threshold": 1.5}, True),
    ({"metal_mu_per_mm": 0.0}, False),
    ({"stream": "disk"}, False),
    ({"name": "fdk_nominal_2"}, True),
    ({"name": "../escape"}, False),
    ({"max_minutes": 0.5}, True),
    ({"max_minutes": 0.0}, False),
    ({"max_minutes": 10081.0}, False),
    ({"device": "cuda"}, True),  # valid everywhere; whether a GPU is usable is found when it runs
    ({"device": "cpu", "algorithm": "pwls", "iterations": 3}, True),
    ({"device": "gpu"}, False),
]


def python_accepts(values: dict[str, Any]) -> bool:
    try:
        checked_options(None, values)
    except ReconError:
        return False
    return True


def rest_accepts(values: dict[str, Any], request: type[BaseModel] = ReconstructionRequest) -> bool:
    """Whether the REST body ``request`` for a scan takes ``values``."""
    try:
        request.model_validate_json(json.dumps({"scan_id": SCAN_ID, **values}))
    except ValidationError:
        return False
    return True


def cli_words(values: dict[str, Any], flags: dict[str, str] = FLAGS) -> list[str]:
    """The options a person types for ``values`` (a flag for True, its ``--no-`` form for False)."""
    words = []
    for name, value in values.items():
        flag = flag_of(name, flags)
        if isinstance(value, bool):
            words.append(flag if value else "--no-" + flag[2:])
        elif isinstance(value, list):
            words += [flag, ",".join(map(str, value))]
        else:
            words += [flag, str(value)]
    return words


def cli_accepts(values: dict[str, Any], scan: Path) -> bool:
    """Parse as ``orbitct reconstruct SCAN ...`` does, then validate as the command does (nothing is run)."""
    try:
        ctx = reconstruct.make_context("reconstruct", [str(scan), *cli_words(values), "--yes"])
        params = {k: v for k, v in ctx.params.items() if k in ReconstructionOptions.model_fields}
        model_from(ReconstructionOptions, params, flags=FLAGS)
    except click.UsageError:
        return False
    return True


@pytest.mark.parametrize(("values", "acceptable"), CASES, ids=[json.dumps(v) for v, _ in CASES])
def test_the_same_options_get_the_same_answer_everywhere(
    values: dict[str, Any], acceptable: bool, tmp_path: Path
) -> None:
    scan = tmp_path / "scan.h5"
    scan.touch()
    answers = {"python": python_accepts(values), "rest": rest_accepts(values), "cli": cli_accepts(values, scan)}
    assert answers == dict.fromkeys(answers, acceptable), answers


def test_every_option_is_in_every_interface() -> None:
    from orbitct_app.reference_pages import openapi_document

    fields = set(ReconstructionOptions.model_fields)
    cli_names = {p.name for p in reconstruct.params}
    assert fields - cli_names == set()
    body = openapi_document()["components"]["schemas"]["ReconstructionRequest"]["properties"]
    assert fields - set(body) == set()
    assert set(body) - fields == {"scan_id"}


def test_a_refusal_names_the_option_as_it_was_typed(tmp_path: Path) -> None:
    scan = tmp_path / "scan.h5"
    scan.touch()
    ctx = reconstruct.make_context("reconstruct", [str(scan), "--voxel-mm", "50", "--grid", "fov"])
    params = {k: v for k, v in ctx.params.items() if k in ReconstructionOptions.model_fields}
    with pytest.raises(click.UsageError, match=r"--voxel-mm: Input should be less than or equal to 20"):
        model_from(ReconstructionOptions, params, flags=FLAGS)


# calibration: (options as Python takes them, with the method, whether they are acceptable)
CALIBRATION_CASES: list[tuple[dict[str, Any], bool]] = [
    ({}, True),
    ({"method": "paper", "iterations": 3}, True),
    ({"method": "magic"}, False),
    ({"iterations": 0}, False),
    ({"iterations": 200}, True),
    ({"iterations": 201}, False),
    ({"intrinsics": "sdd+pp"}, True),
    ({"intrinsics": "all"}, False),
    ({"method": "paper", "intrinsics": "sdd"}, False),
    ({"max_predicted_px": 0.0}, False),
    ({"max_predicted_px": 2.0}, True),
    ({"bridge_max_views": -1}, False),
    ({"min_bbs_per_view": 2}, False),
    ({"min_bbs_per_view": 4}, True),
    ({"diameter_mm": 0.1}, False),
    ({"diameter_mm": 3.17}, True),
    ({"diameter_mm": 51.0}, False),
    ({"scale_bar_mm": 100.0, "scale_bar_bbs": [2, 7]}, True),
    ({"scale_bar_bbs": [2, 7]}, False),  # which BBs, but no length
    ({"scale_bar_mm": 100.0, "scale_bar_bbs": [2, 2]}, False),
    ({"scale_bar_mm": 100.0, "scale_bar_bbs": [0, 7]}, False),
    ({"scale_bar_mm": -5.0}, False),
    ({"k_sigma": 4.5, "max_candidates": 64, "outlier_px": 2.0, "jitter_mm": 8.0}, True),
    ({"k_sigma": 0.0}, False),
    ({"recover": False, "weigh_detections": False}, True),
    ({"loss_scale_px": 0.5, "min_observations": 12}, True),
    ({"min_observations": 1}, False),
    ({"bb_search": "predicted"}, True),
    ({"bb_search": "windows"}, False),
]


def calibration_python_accepts(values: dict[str, Any]) -> bool:
    options = dict(values)
    try:
        checked_calibration_options(options.pop("method", "bundle"), options)
    except OptionError:
        return False
    return True


def calibration_cli_accepts(values: dict[str, Any], scan: Path) -> bool:
    """Parse as ``orbitct calibrate SCAN ...`` does, then validate as the command does (nothing is run)."""
    words = cli_words(values, {})
    try:
        ctx = calibrate.make_context("calibrate", [str(scan), *words])
        params = {k: v for k, v in ctx.params.items() if k in CalibrationOptions.model_fields}
        model_from(CalibrationOptions, params)
    except click.UsageError:
        return False
    return True


@pytest.mark.parametrize(("values", "acceptable"), CALIBRATION_CASES, ids=[json.dumps(v) for v, _ in CALIBRATION_CASES])
def test_a_calibration_gets_the_same_answer_everywhere(
    values: dict[str, Any], acceptable: bool, tmp_path: Path
) -> None:
    scan = tmp_path / "scan.h5"
    scan.touch()
    answers = {
        "python": calibration_python_accepts(values),
        "rest": rest_accepts(values, CalibrationRequest),
        "cli": calibration_cli_accepts(values, scan),
    }
    assert answers == dict.fromkeys(answers, acceptable), answers


def test_every_calibration_option_is_in_every_interface() -> None:
    from orbitct_app.reference_pages import openapi_document

    fields = set(CalibrationOptions.model_fields)
    assert fields - {p.name for p in calibrate.params} == set()
    body = openapi_document()["components"]["schemas"]["CalibrationRequest"]["properties"]
    assert fields - set(body) == set() and set(body) - fields == {"scan_id"}
    rest = CalibrationRequest.model_validate_json(json.dumps({"scan_id": SCAN_ID}))
    assert rest.model_dump(exclude={"scan_id"}) == CalibrationOptions().model_dump()


def test_a_calibration_refusal_names_the_option() -> None:
    with pytest.raises(OptionError, match=r"^iterations: Input should be less than or equal to 200$"):
        checked_calibration_options("bundle", {"iterations": 500})
    with pytest.raises(OptionError, match=r"colour: unknown option; allowed are method, iterations"):
        checked_calibration_options("bundle", {"colour": "red"})
    with pytest.raises(OptionError, match=r"method: must be one of bundle, paper, got 'magic'"):
        checked_calibration_options("magic", {})


def test_the_defaults_are_one_set() -> None:
    options = ReconstructionOptions()
    assert options.algorithm == "fdk" and options.iterations == 50 and options.beta == 0.01
    rest = ReconstructionRequest.model_validate_json(json.dumps({"scan_id": SCAN_ID}))
    assert rest.model_dump(exclude={"scan_id"}) == options.model_dump()


# a scan: (options as Python takes them, whether they are acceptable); orbit parameters go as -p / "params"
SCAN_CASES: list[tuple[dict[str, Any], bool]] = [
    ({}, True),
    ({"orbit": "dcarc", "frames": 300, "mode": "continuous", "frame_rate_hz": 10.0}, True),
    ({"orbit": "spiral"}, False),
    ({"frames": 1}, False),
    ({"frames": 2}, True),
    ({"frames": 100_000}, True),
    ({"frames": 100_001}, False),
    ({"errors": "bench", "seed": 7}, True),
    ({"errors": "sometimes"}, False),
    ({"seed": -1}, False),
    ({"seed": 2**32 - 1}, True),
    ({"seed": 2**32}, False),
    ({"mode": "helical"}, False),
    ({"frame_rate_hz": 0.0}, False),
    ({"frame_rate_hz": 0.005}, True),
    ({"frame_rate_hz": 1000.5}, False),
    ({"orbit_params": {"amplitude_deg": 8}}, True),
    ({"errors": "custom", "error_params": {"angle_noise_deg": [0.1, 0, 0]}}, True),
    # calibrating while the scan runs
    ({"calibrate": "live", "bb_diameter_mm": 3.17, "abort_on": ["bb_lost", "object_moved"]}, True),
    ({"calibrate": "live", "bb_diameter_mm": 50.0, "lost_frames": 10_000}, True),
    ({"calibrate": "live", "bb_diameter_mm": 0.1}, False),
    ({"calibrate": "live", "bb_diameter_mm": 51.0}, False),
    ({"calibrate": "live", "abort_on": ["bb_found"]}, False),  # the good news stops nothing
    ({"abort_on": ["bb_lost"]}, False),  # without calibrate live
    ({"calibrate": "sometimes"}, False),
    ({"calibrate": "live", "lost_frames": 0}, False),
]


LIVE_FIELDS = ("calibrate", "bb_diameter_mm", "abort_on", "lost_frames")


def scan_python_accepts(values: dict[str, Any]) -> bool:
    """A scan request, and the live calibration's options as the subscriber is made from them."""
    from acquire.errors import AcquireError
    from acquire.runner import ScanRequest
    from orbitct_app.live_options import LiveCalibrationOptions

    scan = {k: v for k, v in values.items() if k not in LIVE_FIELDS}
    live = {k: v for k, v in values.items() if k in LIVE_FIELDS}
    try:
        ScanRequest(config="config/bench.yaml", out="scan.h5", **scan).options()
        LiveCalibrationOptions.model_validate(live)
    except (AcquireError, ValidationError):
        return False
    return True


def scan_rest_accepts(values: dict[str, Any]) -> bool:
    from orbitct_app.service.routers.scans import ScanCreate

    body = {("params" if k == "orbit_params" else k): v for k, v in values.items()}
    try:
        ScanCreate.model_validate_json(json.dumps(body))
    except ValidationError:
        return False
    return True


def scan_cli_accepts(values: dict[str, Any]) -> bool:
    """Parse as ``orbitct scan ...`` does, then validate as the command does (nothing is run)."""
    from acquire.options import ScanOptions
    from orbitct_app.cli.scan import FLAGS as SCAN_FLAGS
    from orbitct_app.cli.scan import scan
    from orbitct_app.live_options import LiveCalibrationOptions

    words = []
    for name, value in values.items():
        if name in ("orbit_params", "error_params"):
            flag = "--param" if name == "orbit_params" else "--error-param"
            words += [w for k, v in value.items() for w in (flag, f"{k}={json.dumps(v)}")]
        elif name == "abort_on":
            words += [w for kind in value for w in ("--abort-on", kind)]
        else:
            words += [flag_of(name, SCAN_FLAGS), str(value)]
    try:
        ctx = scan.make_context("scan", words)
        params = {k: v for k, v in ctx.params.items() if k in ScanOptions.model_fields}
        params["orbit_params"] = {k: v for item in ctx.params["params"] for k, v in [_key_value(item)]}
        params["error_params"] = {k: v for item in ctx.params["error_params"] for k, v in [_key_value(item)]}
        model_from(ScanOptions, params, flags=SCAN_FLAGS)
        live = {k: v for k, v in ctx.params.items() if k in LIVE_FIELDS}
        model_from(LiveCalibrationOptions, {**live, "abort_on": list(live["abort_on"])})
    except click.UsageError:
        return False
    return True


def _key_value(item: str) -> tuple[str, Any]:
    key, _, value = item.partition("=")
    return key, json.loads(value)


@pytest.mark.parametrize(("values", "acceptable"), SCAN_CASES, ids=[json.dumps(v) for v, _ in SCAN_CASES])
def test_a_scan_gets_the_same_answer_everywhere(values: dict[str, Any], acceptable: bool) -> None:
    answers = {
        "python": scan_python_accepts(values),
        "rest": scan_rest_accepts(values),
        "cli": scan_cli_accepts(values),
    }
    assert answers == dict.fromkeys(answers, acceptable), answers


def test_every_scan_option_is_in_every_interface() -> None:
    from acquire.options import ScanOptions
    from orbitct_app.cli.scan import scan
    from orbitct_app.live_options import LiveCalibrationOptions
    from orbitct_app.reference_pages import openapi_document
    from orbitct_app.service.routers.scans import ScanCreate

    fields = set(ScanOptions.model_fields) | set(LiveCalibrationOptions.model_fields)
    cli_names = {p.name for p in scan.params} | {"orbit_params"}  # -p KEY=VALUE
    assert fields - cli_names == set()
    body = set(openapi_document()["components"]["schemas"]["ScanCreate"]["properties"]) - {"params"}
    assert fields - {"orbit_params"} - body == set()
    assert body - fields == {"name"}  # the service's own label
    rest = ScanCreate.model_validate_json("{}")
    defaults = ScanOptions().model_dump() | LiveCalibrationOptions().model_dump()
    assert rest.model_dump(include=fields) == defaults


def test_a_scan_refusal_names_the_option() -> None:
    from acquire.errors import AcquireError
    from acquire.options import checked_scan_options

    with pytest.raises(AcquireError, match=r"^frames: Input should be greater than or equal to 2$"):
        checked_scan_options(frames=1)
    with pytest.raises(AcquireError, match=r"^orbit: unknown orbit 'spiral'; choose one of circular, sawtooth"):
        checked_scan_options(orbit="spiral")
    with pytest.raises(AcquireError, match=r"^colour: unknown option; allowed are orbit, orbit_params"):
        checked_scan_options(colour="red")


# a BB plan: (options as Python takes them, whether they are acceptable); experiment A unless given
PLAN_CASES: list[tuple[dict[str, Any], bool]] = [
    ({}, True),
    ({"experiment": "b", "orbit": "circular", "frames": 90}, True),
    ({"experiment": "D"}, False),
    ({"frames": 1}, False),
    ({"frames": 5000}, True),
    ({"frames": 5001}, False),
    ({"bbs": 3}, False),
    ({"bbs": 40}, True),
    ({"bbs": 41}, False),
    ({"target_px": 0.0}, False),
    ({"target_px": 10.0, "max_bbs": 12}, True),
    ({"target_px": 10.5}, False),
    ({"max_bbs": 41}, False),
    ({"detector_px": 7}, False),
    ({"detector_px": 4096}, True),
    ({"errors": "bench", "noise_px": 5.0, "seed": 2**32 - 1}, True),
    ({"errors": "sometimes"}, False),
    ({"noise_px": 0.0}, False),
    ({"noise_px": 5.5}, False),
    ({"seed": 2**32}, False),
    ({"keep_out": [{"angle_from_deg": 300.0, "angle_to_deg": 60.0, "z_min_mm": -20.0, "z_max_mm": 10.0}]}, True),
    ({"keep_out": [{"angle_from_deg": 10.0, "angle_to_deg": 20.0, "z_min_mm": 5.0, "z_max_mm": 5.0}]}, False),
    ({"keep_out": [{"angle_from_deg": 10.0, "angle_to_deg": 20.0, "z_min_mm": 0.0, "z_max_mm": 1001.0}]}, False),
    ({"surface_threshold_per_mm": 0.02}, True),
    ({"surface_threshold_per_mm": 0.0}, False),
]


def plan_python_accepts(values: dict[str, Any]) -> bool:
    from orbitct_app.bbplan import BBPlanError, BBPlanRequest

    try:
        BBPlanRequest.checked(**{"experiment": "A", **values})
    except BBPlanError:
        return False
    return True


def plan_rest_accepts(values: dict[str, Any]) -> bool:
    from orbitct_app.service.routers.plans import BBPlanIn

    try:
        BBPlanIn.model_validate_json(json.dumps({"experiment": "A", **values}))
    except ValidationError:
        return False
    return True


def plan_cli_accepts(values: dict[str, Any], tmp_path: Path) -> bool:
    """Parse as ``orbitct plan bbs ...`` does, then validate as the command does (nothing is planned)."""
    from orbitct_app.bbplan_options import BBPlanOptions
    from orbitct_app.cli.plan import FLAGS as PLAN_FLAGS
    from orbitct_app.cli.plan import bbs

    words = ["--experiment", values.get("experiment", "A"), "--out", str(tmp_path / "plan.json")]
    for name, value in values.items():
        if name == "keep_out":
            for z in value:
                text = f"{z['angle_from_deg']}:{z['angle_to_deg']},{z['z_min_mm']}:{z['z_max_mm']}"
                words += ["--keep-out", text]
        elif name != "experiment":
            words += [flag_of(name, PLAN_FLAGS), str(value)]
    try:
        ctx = bbs.make_context("bbs", words)
        given = {k: v for k, v in ctx.params.items() if k in BBPlanOptions.model_fields}
        zones = [dataclasses.asdict(z) for z in ctx.params["keep_out"]]
        model_from(BBPlanOptions, {**given, "keep_out": zones}, flags=PLAN_FLAGS)
    except click.UsageError:
        return False
    return True


@pytest.mark.parametrize(("values", "acceptable"), PLAN_CASES, ids=[json.dumps(v) for v, _ in PLAN_CASES])
def test_a_bb_plan_gets_the_same_answer_everywhere(values: dict[str, Any], acceptable: bool, tmp_path: Path) -> None:
    answers = {
        "python": plan_python_accepts(values),
        "rest": plan_rest_accepts(values),
        "cli": plan_cli_accepts(values, tmp_path),
    }
    assert answers == dict.fromkeys(answers, acceptable), answers


def test_every_bb_plan_option_is_in_every_interface() -> None:
    from orbitct_app.bbplan_options import BBPlanOptions
    from orbitct_app.cli.plan import bbs
    from orbitct_app.reference_pages import openapi_document
    from orbitct_app.service.routers.plans import BBPlanIn

    fields = set(BBPlanOptions.model_fields)
    assert fields - {p.name for p in bbs.params} == set()
    body = set(openapi_document()["components"]["schemas"]["BBPlanIn"]["properties"])
    assert body - fields == {"surface_id", "surface_reconstruction_id", "surface_shape"}  # where the surface is
    assert fields - body == set()
    rest = BBPlanIn.model_validate_json('{"experiment": "A"}')
    assert rest.model_dump(include=fields) == BBPlanOptions(experiment="A").model_dump()


# a DICOM export: (options as Python takes them, whether they are acceptable)
DICOM_CASES: list[tuple[dict[str, Any], bool]] = [
    ({}, True),
    ({"water_mu_per_mm": 0.019, "patient_name": "Phantom^Leg", "patient_id": "leg 1", "enhanced": True}, True),
    ({"water_mu_per_mm": 0.0}, False),
    ({"water_mu_per_mm": 10.5}, False),
    ({"patient_id": "leg/1"}, False),
    ({"patient_id": "x" * 65}, False),
    ({"patient_name": "Phantom\\Leg"}, False),  # a backslash separates DICOM values
    ({"study_description": "knee, 500 views"}, True),
    ({"study_description": "y" * 65}, False),
]


DOWNLOAD = FastAPI()


@DOWNLOAD.get("/dicom")
def _download(options: Annotated[DicomSeriesOptions, Query()]) -> dict[str, Any]:
    """A route that reads its query as ``GET /reconstructions/{id}/dicom`` does."""
    return options.model_dump()


def dicom_cli_accepts(values: dict[str, Any], tmp_path: Path) -> bool:
    """Parse as ``orbitct export dicom SCAN ...`` does, then validate as the command does (nothing is written)."""
    from orbitct.dicom import DicomSeriesOptions
    from orbitct_app.cli.export import dicom

    scan = tmp_path / "scan.h5"
    scan.touch()
    words = [str(scan), "--recon", "fdk", "--out", str(tmp_path / "series")]
    for name, value in values.items():
        words += [flag_of(name, {})] if value is True else [flag_of(name, {}), str(value)]
    try:
        ctx = dicom.make_context("dicom", words)
        model_from(DicomSeriesOptions, {k: v for k, v in ctx.params.items() if k in DicomSeriesOptions.model_fields})
    except click.UsageError:
        return False
    return True


@pytest.mark.parametrize(("values", "acceptable"), DICOM_CASES, ids=[json.dumps(v) for v, _ in DICOM_CASES])
def test_a_dicom_export_gets_the_same_answer_everywhere(
    values: dict[str, Any], acceptable: bool, tmp_path: Path
) -> None:
    from fastapi.testclient import TestClient

    from orbitct.dicom import DicomSeriesOptions
    from orbitct_app.service.routers.pacs import SendRequest

    def python() -> bool:
        try:
            DicomSeriesOptions.model_validate(values)
        except ValidationError:
            return False
        return True

    def rest_store() -> bool:
        try:
            SendRequest.model_validate_json(json.dumps({"reconstruction_id": "r1", **values}))
        except ValidationError:
            return False
        return True

    def rest_download() -> bool:  # the query of GET /reconstructions/{id}/dicom, as FastAPI reads it
        return TestClient(DOWNLOAD).get("/dicom", params=values).status_code == 200

    answers = {
        "python": python(),
        "rest_store": rest_store(),
        "rest_download": rest_download(),
        "cli": dicom_cli_accepts(values, tmp_path),
    }
    assert answers == dict.fromkeys(answers, acceptable), answers


def test_every_dicom_option_is_in_every_interface() -> None:
    from orbitct.dicom import DicomSeriesOptions
    from orbitct_app.cli.export import dicom
    from orbitct_app.reference_pages import openapi_document

    fields = set(DicomSeriesOptions.model_fields)
    assert fields - {p.name for p in dicom.params} == set()
    paths = openapi_document()["paths"]
    query = {p["name"] for p in paths["/reconstructions/{job_id}/dicom"]["get"]["parameters"] if p["in"] == "query"}
    assert query == fields
    body = set(openapi_document()["components"]["schemas"]["SendRequest"]["properties"])
    assert body - fields == {"reconstruction_id"} and fields - body == set()


def test_python_takes_numpy_numbers_as_the_api_takes_json_ones() -> None:
    """Scripts pass numbers numpy made (a seed drawn from a generator, a count from an array): the Python API takes
    them as Python's own; only the REST requests, which are JSON, are strict about types."""
    import numpy as np

    from acquire.runner import ScanRequest
    from orbitct_app.bbplan import BBPlanRequest
    from orbitct_app.live_options import LiveCalibrationOptions

    scan = ScanRequest(config="config/bench.yaml", out="s.h5", frames=np.int64(40), seed=np.int64(7)).options()
    assert scan.frames == 40 and scan.seed == 7
    plan = BBPlanRequest.checked(experiment="A", bbs=np.int64(9), noise_px=np.float32(0.2)).options
    assert plan.bbs == 9 and abs(plan.noise_px - 0.2) < 1e-6
    assert LiveCalibrationOptions(lost_frames=np.int64(5)).lost_frames == 5
