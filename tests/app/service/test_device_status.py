"""A device's read-back in the operator's terms: the named state, each axis with its unit and soft limits, the
generator's readings with units; the latch and a fault come first."""

from __future__ import annotations

from typing import Any

import pytest

from orbitct_app.service.rig.status import STATES, device_status

HEXAPOD = {"name": "hexapod", "axes": [{"name": "X", "unit": "mm", "low": -50.0, "high": 50.0}]}
XRAY = {"name": "xray", "axes": []}


def _axis_state(**over: Any) -> dict[str, Any]:
    state = {
        "position": {"X": 1.25},
        "target": {"X": 1.25},
        "on_target": {"X": True},
        "referenced": {"X": True},
        "servo": {"X": True},
        "moving": {"X": False},
    }
    return {**state, **over}


@pytest.mark.parametrize(
    ("over", "latched", "status"),
    [
        ({}, False, "on target"),
        ({"on_target": {"X": False}}, False, "referenced"),
        ({"referenced": {"X": False}}, False, "not referenced"),
        ({"servo": {"X": False}}, False, "servo off"),
        ({"moving": {"X": True}}, False, "moving"),
        ({"moving": True}, False, "moving"),  # one flag for the whole device
        ({"moving": False, "on_target": True, "referenced": True}, False, "on target"),
        ({}, True, "latched"),
    ],
)
def test_a_motion_device_gets_one_named_state(over: dict[str, Any], latched: bool, status: str) -> None:
    named = device_status(HEXAPOD, _axis_state(**over), latched)
    assert named["status"] == status and named["tone"] == STATES[status] and named["why"]
    axis = named["axes"][0]
    assert axis["position"] == "1.250 mm" and axis["limits"] == "-50 … 50 mm" and axis["unit"] == "mm"


def _xray_state(**over: Any) -> dict[str, Any]:
    state = {
        "state": "IDLE",
        "fault_code": 0,
        "fault": "NONE",
        "door_closed": True,
        "ready": False,
        "exposing": False,
        "hv_on": False,
        "kv": 80.0,
        "ma": 2.0,
        "exposure_ms": 20,
        "kv_actual": 0.0,
        "ma_actual": 0.0,
        "frame_counter": 12,
    }
    return {**state, **over}


@pytest.mark.parametrize(
    ("over", "latched", "status"),
    [
        ({}, False, "standby"),
        ({"ready": True}, False, "ready"),
        ({"hv_on": True}, False, "high voltage on"),
        ({"exposing": True, "hv_on": True}, False, "exposing"),
        ({"door_closed": False}, False, "door open"),
        ({"fault": "INTERLOCK_OPENED", "fault_code": 1, "state": "FAULT"}, False, "fault"),
        ({"fault": "INTERLOCK_OPENED", "fault_code": 1, "state": "FAULT"}, True, "fault"),
        ({}, True, "latched"),
    ],
)
def test_the_generator_gets_one_named_state_and_readings_with_units(
    over: dict[str, Any], latched: bool, status: str
) -> None:
    named = device_status(XRAY, _xray_state(**over), latched)
    assert named["status"] == status and named["tone"] == STATES[status], named
    values = {r["label"]: r["value"] for r in named["readings"]}
    assert values["high voltage set"] == "80.0 kV" and values["tube current set"] == "2.00 mA"
    assert values["exposure time"] == "20 ms" and "fault_code" not in str(named)
    if status == "fault":
        assert "door opened while high voltage was on" in named["why"] and "reset" in named["why"]


def test_a_panel_is_armed_or_standing_by() -> None:
    state = {"armed": 1, "mode": "XRAY", "frames": 3, "queued": 0, "binning": 1, "shape": (64, 96)}
    named = device_status({"name": "detector", "axes": []}, state, False)
    values = {r["label"]: r["value"] for r in named["readings"]}
    assert named["status"] == "armed" and values["frame size"] == "96 × 64 pixels"
    assert values["trigger"] == "per exposure" and values["frames taken"] == "3"
    assert device_status({"name": "detector", "axes": []}, {**state, "armed": 0}, False)["status"] == "standby"


def test_a_position_of_almost_zero_reads_zero_not_minus_zero() -> None:
    named = device_status(HEXAPOD, _axis_state(position={"X": -0.00001}), False)
    assert named["axes"][0]["position"] == "0.000 mm"
