"""A device's read-back in the operator's terms: one named state with its reason, each axis with its position, target
and soft limits in its unit, and the other readings labelled with their units, instead of register values."""

from __future__ import annotations

import math
from typing import Any

# the named states, most urgent first; "alarm": red on the console, "ok": green, "idle": plain
STATES: dict[str, str] = {
    "latched": "alarm",
    "fault": "alarm",
    "moving": "alarm",
    "exposing": "alarm",
    "high voltage on": "alarm",
    "not referenced": "idle",
    "servo off": "idle",
    "on target": "ok",
    "referenced": "ok",
    "ready": "ok",
    "armed": "ok",
    "standby": "idle",
    "door open": "idle",
}
FAULT_WORDS = {
    "INTERLOCK_OPENED": "the door opened while high voltage was on",
    "WATCHDOG": "orbitct's heartbeat stopped while high voltage was on",
    "GENERATOR": "an internal generator fault (arc, over-temperature)",
    "INVALID_SETTINGS": "kV, mA or exposure time out of range",
    "UNKNOWN": "a fault code the generator does not document",
}


def _number(value: Any, unit: str, digits: int = 3) -> str:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        return "—"
    if abs(value) < 0.5 * 10.0**-digits:  # no "-0.000"
        value = 0.0
    return f"{value:.{digits}f} {unit}".strip()


def _yes(value: Any) -> str:
    return "yes" if value else "no"


def _per_axis(state: dict[str, Any], key: str, axis: str) -> Any:
    """``state[key]`` for one axis: a value per axis, or one value for the whole device (a C-arm's ``moving``)."""
    value = state.get(key)
    return value.get(axis) if isinstance(value, dict) else value


def _axes(device: dict[str, Any], state: dict[str, Any]) -> list[dict[str, Any]]:
    """Each axis: position and target in its unit, soft limits, referenced and on target."""
    rows = []
    for axis in device.get("axes", []):
        name, unit = axis["name"], axis.get("unit", "")
        rows.append(
            {
                "axis": name,
                "unit": unit,
                "position": _number(_per_axis(state, "position", name), unit),
                "target": _number(_per_axis(state, "target", name), unit),
                "limits": f"{axis['low']:g} … {axis['high']:g} {unit}".strip(),
                "referenced": bool(_per_axis(state, "referenced", name)),
                "on_target": bool(_per_axis(state, "on_target", name)),
                "moving": bool(_per_axis(state, "moving", name)),
            }
        )
    return rows


def _motion(state: dict[str, Any], axes: list[dict[str, Any]]) -> tuple[str, str]:
    if state.get("moving") is True:  # one flag for the whole device (PI's #5, the C-arm's POS?)
        return "moving", "the axes are moving"
    moving = [a["axis"] for a in axes if a["moving"]]
    if moving:
        return "moving", f"{', '.join(moving)} moving"
    if not axes:
        return "standby", "no axes to read back"
    unreferenced = [a["axis"] for a in axes if not a["referenced"]]
    if unreferenced:
        return "not referenced", f"{', '.join(unreferenced)} not referenced: reference before scanning"
    servo = state.get("servo") or {}
    off = [a for a, on in servo.items() if not on] if isinstance(servo, dict) else []
    if off:
        return "servo off", f"servo off on {', '.join(off)}"
    away = [a["axis"] for a in axes if not a["on_target"]]
    if away:
        return "referenced", f"referenced; {', '.join(away)} not on target"
    return "on target", "referenced, every axis on target"


def _xray(state: dict[str, Any]) -> tuple[str, str, list[dict[str, str]]]:
    fault = str(state.get("fault") or "NONE")
    readings = [
        {"label": "high voltage set", "value": _number(state.get("kv"), "kV", 1)},
        {"label": "high voltage now", "value": _number(state.get("kv_actual"), "kV", 1)},
        {"label": "tube current set", "value": _number(state.get("ma"), "mA", 2)},
        {"label": "tube current now", "value": _number(state.get("ma_actual"), "mA", 2)},
        {"label": "exposure time", "value": _number(state.get("exposure_ms"), "ms", 0)},
        {"label": "door", "value": "closed" if state.get("door_closed") else "open"},
        {"label": "exposures since power-on", "value": str(state.get("frame_counter", "—"))},
    ]
    if fault != "NONE" or state.get("state") == "FAULT":
        why = FAULT_WORDS.get(fault, fault.lower().replace("_", " "))
        return "fault", f"generator fault: {why}; reset it once the cause is gone", readings
    if state.get("exposing"):
        return "exposing", "X-rays on", readings
    if state.get("hv_on"):
        return "high voltage on", "high voltage on, not exposing", readings
    if not state.get("door_closed", True):
        return "door open", "the door is open: no X-rays until it is closed", readings
    if state.get("ready"):
        return "ready", "prepared for an exposure", readings
    return "standby", "X-rays off", readings


def _detector(state: dict[str, Any]) -> tuple[str, str, list[dict[str, str]]]:
    shape = state.get("shape")
    readings = [{"label": "frame size", "value": f"{shape[1]} × {shape[0]} pixels" if shape else "—"}]
    named = (
        ("frames", "frames taken"),
        ("queued", "frames waiting"),
        ("waiting", "files waiting"),
        ("binning", "binning"),
    )
    for key, label in named:
        if key in state:
            readings.append({"label": label, "value": str(state[key])})
    if "mode" in state:
        readings.append({"label": "trigger", "value": "per exposure" if state["mode"] == "XRAY" else "software"})
    armed = state.get("armed")
    if armed in (1, True, "1"):
        return "armed", "armed: takes a frame per trigger", readings
    return "standby", "not armed", readings


def device_status(device: dict[str, Any], state: dict[str, Any], latched: bool) -> dict[str, Any]:
    """The named state (:data:`STATES`) with its reason, the axes and the labelled readings of one device."""
    axes = _axes(device, state)
    readings: list[dict[str, str]] = []
    if "fault_code" in state:  # an X-ray generator
        name, why, readings = _xray(state)
    elif axes or "moving" in state:  # a hexapod, a rotation stage, a C-arm
        name, why = _motion(state, axes)
        if "primary_deg" in state:
            readings = [
                {"label": "primary angle", "value": _number(state.get("primary_deg"), "°", 2)},
                {"label": "secondary angle", "value": _number(state.get("secondary_deg"), "°", 2)},
                {"label": "program point", "value": str(state.get("point", "—"))},
            ]
    else:  # a flat panel
        name, why, readings = _detector(state)
    if latched and name not in ("fault",):
        name, why = "latched", f"the emergency stop is latched: no motion or X-rays until an operator resets it ({why})"
    return {"status": name, "tone": STATES[name], "why": why, "axes": axes, "readings": readings}
