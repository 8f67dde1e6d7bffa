"""PI's own PIPython drives the hexapod twin through its pure-socket gateway, as it would a real C-887."""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest
from pipython import GCSDevice, GCSError
from pipython.pidevice.interfaces.pisocket import PISocket

from devices.twins.runtime import TwinThread

pytestmark = pytest.mark.system


class _Gateway(PISocket):
    """PIPython's socket gateway, with a close that may be called twice (PIPython closes again on delete)."""

    def close(self) -> None:
        if self.connected:
            super().close()


@pytest.fixture
def pidevice(hexapod_twin: TwinThread) -> Iterator[GCSDevice]:
    gateway = _Gateway(autoconnect=False)
    gateway.ConnectTCPIP(ipaddress=hexapod_twin.host, ipport=hexapod_twin.port)
    with GCSDevice(gateway=gateway) as dev:  # leaving unregisters PIPython's (class-wide) connection callback
        yield dev


def _wait(predicate, timeout_s: float = 10.0) -> None:  # type: ignore[no-untyped-def]
    t0 = time.monotonic()
    while not predicate():
        assert time.monotonic() - t0 < timeout_s, "timed out"
        time.sleep(0.01)


def test_identify(pidevice: GCSDevice) -> None:
    assert "C-887" in pidevice.qIDN()
    assert pidevice.devname.startswith("C-887")
    assert pidevice.axes == ["X", "Y", "Z", "U", "V", "W"]
    assert pidevice.qTMX("X")["X"] == 50.0 and pidevice.qTMN("W")["W"] == -30.0


def test_reference_move_read_back(pidevice: GCSDevice, hexapod_twin: TwinThread) -> None:
    pidevice.SVO(pidevice.axes, [True] * 6)
    pidevice.FRF()
    _wait(pidevice.IsControllerReady)
    assert all(pidevice.qFRF().values())
    pidevice.VLS(20.0)
    pidevice.MOV({"X": 1.5, "Z": -0.5, "V": 2.0})
    _wait(lambda: not any(pidevice.IsMoving().values()))
    assert all(pidevice.qONT().values())
    pos = pidevice.qPOS()
    assert pos["X"] == pytest.approx(1.5, abs=1e-3) and pos["V"] == pytest.approx(2.0, abs=1e-3)
    assert pidevice.qMOV("Z")["Z"] == pytest.approx(-0.5)
    assert pidevice.qVMO(["X", "Y", "U"], [50.0, 50.0, 30.0]) is False
    assert pidevice.qVMO("X", 3.0) is True


def test_out_of_limit_move_refused_with_error_7(pidevice: GCSDevice, hexapod_twin: TwinThread) -> None:
    pidevice.SVO(pidevice.axes, [True] * 6)
    pidevice.FRF()
    _wait(pidevice.IsControllerReady)
    with pytest.raises(GCSError) as info:
        pidevice.MOV("X", 60.0)
    assert info.value.val == 7
    with pytest.raises(GCSError) as info:
        pidevice.MOV({"X": 50.0, "Y": 50.0, "U": 30.0, "V": 30.0})  # each axis fine, the pose is not
    assert info.value.val == 7
    assert not hexapod_twin.twin.controller.is_moving()


def test_unreferenced_move_refused_with_error_5(pidevice: GCSDevice) -> None:
    pidevice.SVO("X", True)
    with pytest.raises(GCSError) as info:
        pidevice.MOV("X", 1.0)
    assert info.value.val == 5


def test_halt(pidevice: GCSDevice, hexapod_twin: TwinThread) -> None:
    pidevice.SVO(pidevice.axes, [True] * 6)
    pidevice.FRF()
    _wait(pidevice.IsControllerReady)
    pidevice.VLS(0.5)
    pidevice.MOV("Y", 30.0)
    assert any(pidevice.IsMoving().values())
    pidevice.HLT(noraise=True)
    assert not any(pidevice.IsMoving().values())
    pidevice.MOV("Y", 30.0)
    with pytest.raises(GCSError) as info:
        pidevice.StopAll()
    assert info.value.val == 10
    assert not hexapod_twin.twin.controller.is_moving()
    assert pidevice.qPOS("Y")["Y"] < 30.0


def test_pi_startup_routine_references_the_hexapod(pidevice: GCSDevice, hexapod_twin: TwinThread) -> None:
    """PI's own start-up (servo on and FRF axis by axis, as on a C-887) brings the twin up; then moves,
    on-target waits and every stop command behave as documented, with the error code after each."""
    from pipython import pitools

    pitools.startup(pidevice, refmodes="FRF")
    assert all(pidevice.qFRF().values()) and all(pidevice.qSVO().values())
    assert pidevice.qERR() == 0
    pidevice.SVO("U", False)  # the hexapod's servo is one switch for all six axes (C-887)
    assert not any(pidevice.qSVO().values())
    pidevice.SVO("U", True)
    assert all(pidevice.qSVO().values())
    pidevice.VLS(20.0)
    pidevice.MOV({"Y": 2.0, "W": 1.0})
    pitools.waitontarget(pidevice, axes=["Y", "W"], timeout=10)
    assert all(pidevice.qONT().values()) and pidevice.qERR() == 0
    assert pidevice.qPOS("Y")["Y"] == pytest.approx(2.0, abs=1e-3)
    for stop in ("STP", "HLT", "StopAll"):
        pidevice.VLS(0.5)
        pidevice.MOV("Z", 10.0)
        assert any(pidevice.IsMoving().values())
        with pytest.raises(GCSError) as info:  # PIPython reads ERR? after the command (StopAll is #24)
            getattr(pidevice, stop)()
        assert info.value.val == 10, stop  # "controller was stopped by command"
        assert not any(pidevice.IsMoving().values()) and not hexapod_twin.twin.controller.is_moving()
        assert pidevice.qERR() == 0  # reading the error cleared it
        pidevice.VLS(20.0)
        pidevice.MOV("Z", 0.0)
        pitools.waitontarget(pidevice, axes="Z", timeout=10)
