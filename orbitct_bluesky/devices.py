"""ophyd-async devices over orbitct's own drivers: the hexapod, the rotation stage, the X-ray generator, the panel.

Each device is written once and reaches its hardware by the URI orbitct uses (``tcp://host:port``,
``serial:///dev/ttyUSB0``, ``modbus://``; ``sim://bench`` starts orbitct's twin on a loopback socket, all four in
one simulated world). The protocol work (PI GCS 2.0, Modbus TCP, the panel's frame link) is orbitct's driver's;
these classes give it ophyd-async's shape: signals to read, ``set`` to move, ``trigger`` to expose, ``stop`` to
halt. Connected with ``mock=True`` there is no driver: a move arrives at once, an exposure counts, the panel
gives dark frames (ophyd-async's mock mode, for plans tested without any hardware).
"""

from __future__ import annotations

import asyncio
from collections.abc import Coroutine, Mapping
from typing import Any

import numpy as np
from ophyd_async.core import (
    DEFAULT_TIMEOUT,
    Array1D,
    AsyncStatus,
    DeviceMock,
    StandardReadable,
    StandardReadableFormat,
    soft_signal_r_and_setter,
    soft_signal_rw,
)

from devices.factory import open_device
from orbitct.scanfile import ImageKey

HEXAPOD_AXES = ("X", "Y", "Z", "U", "V", "W")
HEXAPOD_UNITS = ("mm", "mm", "mm", "deg", "deg", "deg")


async def _to_the_end(safety: Coroutine[Any, Any, None]) -> None:
    """Run a halt or X-rays-off in a task of its own, never cut short: the RunEngine calls them from a task it is
    cancelling (a pause, an abort), and a driver gives up a request in a task that is being cancelled."""
    await asyncio.shield(asyncio.ensure_future(safety))


class DriverDevice(StandardReadable):
    """An ophyd-async device whose hardware is one orbitct driver, opened at :meth:`connect` from ``uri``."""

    kind = ""

    def __init__(self, uri: str, name: str = "", **options: Any) -> None:
        self.uri = uri
        self.options = dict(options)
        self._driver: Any = None
        self._mocked = False
        super().__init__(name=name)

    async def connect(
        self, mock: bool | DeviceMock[Any] = False, timeout: float = DEFAULT_TIMEOUT, force_reconnect: bool = False
    ) -> None:
        """Connect the signals, then (not in mock mode) open the driver at ``uri`` (a ``sim://`` twin starts)."""
        await super().connect(mock=mock, timeout=timeout, force_reconnect=force_reconnect)
        self._mocked = bool(mock)
        if self._mocked or (self._driver is not None and not force_reconnect):
            return
        if self._driver is not None:
            await self.disconnect()
        opening = open_device(self.kind, self.name or self.kind, self.uri, **self.options)
        self._driver = await asyncio.wait_for(opening, timeout)

    async def disconnect(self) -> None:
        """Close the driver (its twin stops with it)."""
        driver, self._driver = self._driver, None
        if driver is not None:
            await driver.close()

    @property
    def driver(self) -> Any:
        """The orbitct driver underneath (for what ophyd-async has no verb for: referencing, limits, servo)."""
        if self._driver is None:
            raise RuntimeError(
                f"{self.name or self.kind} is not connected to {self.uri}"
                + (" (connected in mock mode: there is no driver)" if self._mocked else ": connect it first")
            )
        return self._driver

    @property
    def simulated(self) -> bool:
        """Whether the device is orbitct's twin (a ``sim://`` URI)."""
        return self.uri.startswith("sim://")


class _Axes(DriverDevice):
    """A motion device: per axis a read-back (read, hinted) and a setpoint (read), moved together by ``set``."""

    axes: tuple[str, ...] = ()
    units: tuple[str, ...] = ()

    def __init__(self, uri: str, name: str = "", **options: Any) -> None:
        self._readback_set: dict[str, Any] = {}
        with self.add_children_as_readables(StandardReadableFormat.HINTED_SIGNAL):
            for axis, unit in zip(self.axes, self.units, strict=True):
                signal, setter = soft_signal_r_and_setter(float, 0.0, units=unit)
                setattr(self, axis, signal)
                self._readback_set[axis] = setter
        with self.add_children_as_readables():
            for axis, unit in zip(self.axes, self.units, strict=True):
                setattr(self, f"{axis}_setpoint", soft_signal_rw(float, 0.0, units=unit))
        super().__init__(uri, name, **options)

    async def _refresh(self) -> None:
        if self._mocked:
            return
        for axis, value in (await self.driver.position()).items():
            if axis in self._readback_set:
                self._readback_set[axis](float(value))

    async def read(self) -> dict[str, Any]:
        """The axes' read-backs (from the controller now) and setpoints."""
        await self._refresh()
        return await super().read()

    async def locate(self) -> dict[str, Any]:
        """Where the axes are and were last sent (ophyd's ``Locatable``)."""
        await self._refresh()
        setpoint = {a: await getattr(self, f"{a}_setpoint").get_value() for a in self.axes}
        readback = {a: await getattr(self, a).get_value() for a in self.axes}
        return {"setpoint": setpoint, "readback": readback}

    def _targets(self, value: Any) -> dict[str, float]:
        if not isinstance(value, Mapping):
            if len(self.axes) != 1:
                raise ValueError(f"{self.name}: set() takes a mapping of axis to target, axes {', '.join(self.axes)}")
            value = {self.axes[0]: value}
        unknown = sorted(set(value) - set(self.axes))
        if unknown:
            raise ValueError(f"{self.name}: no axis {', '.join(unknown)}; its axes are {', '.join(self.axes)}")
        return {str(a): float(v) for a, v in value.items()}

    @AsyncStatus.wrap
    async def set(self, value: Any) -> None:
        """Move to ``value`` (a mapping of axis to target, or one number for a one-axis device) and wait there;
        the controller checks its limits before anything moves."""
        targets = self._targets(value)
        for axis, target in targets.items():
            await getattr(self, f"{axis}_setpoint").set(target)
        if self._mocked:
            for axis, target in targets.items():
                self._readback_set[axis](target)
            return
        await self.driver.move(targets)
        await self._refresh()

    async def stop(self, success: bool = True) -> None:
        """Halt every axis of the device now (the bluesky ``Stoppable`` protocol)."""
        if not self._mocked and self._driver is not None:
            await _to_the_end(self._driver.stop())


class Hexapod(_Axes):
    """The PI hexapod (GCS 2.0): X, Y, Z in mm, U, V, W in degrees."""

    kind = "hexapod"
    axes = HEXAPOD_AXES
    units = HEXAPOD_UNITS


class RotationStage(_Axes):
    """The PI rotation stage (GCS 2.0): one axis, R, in degrees."""

    kind = "rotation_stage"
    axes = ("R",)
    units = ("deg",)


class XrayGenerator(DriverDevice):
    """The X-ray generator (Modbus TCP): ``set`` the technique, ``trigger`` one exposure; ``stop`` and ``pause``
    switch high voltage off. Read: the frame counter; configuration: kV, mA and exposure time."""

    kind = "xray"

    def __init__(self, uri: str, name: str = "", **options: Any) -> None:
        with self.add_children_as_readables():
            self.frame_counter, self._set_counter = soft_signal_r_and_setter(int, 0)
        with self.add_children_as_readables(StandardReadableFormat.CONFIG_SIGNAL):
            self.kv, self._set_kv = soft_signal_r_and_setter(float, 0.0, units="kV")
            self.ma, self._set_ma = soft_signal_r_and_setter(float, 0.0, units="mA")
            self.exposure_ms, self._set_exposure = soft_signal_r_and_setter(float, 0.0, units="ms")
        #: high voltage off at once after each exposure (the next is further away than a preparation)
        self.release = True
        super().__init__(uri, name, **options)

    @AsyncStatus.wrap
    async def set(self, value: Mapping[str, float]) -> None:
        """Set the technique, ``{"kv": ..., "ma": ..., "exposure_ms": ...}`` (the generator checks its ranges).
        A plan sets it in its run: the RunEngine then stops the generator, X-rays off, however the run ends."""
        missing = sorted({"kv", "ma", "exposure_ms"} - set(value))
        if missing:
            raise ValueError(f"{self.name}: set() takes kv, ma and exposure_ms; {', '.join(missing)} missing")
        kv, ma, exposure_ms = float(value["kv"]), float(value["ma"]), float(value["exposure_ms"])
        if not self._mocked:
            await self.driver.configure(kv, ma, exposure_ms)
        self._set_kv(kv)
        self._set_ma(ma)
        self._set_exposure(exposure_ms)

    @AsyncStatus.wrap
    async def trigger(self) -> None:
        """One exposure (prepared first if the source is not ready); done when X-rays are off again."""
        if self._mocked:
            self._set_counter(await self.frame_counter.get_value() + 1)
            return
        self._set_counter(int(await self.driver.expose(release=self.release)))

    async def xray_off(self) -> None:
        """Drop prep and expose requests and switch high voltage off."""
        if not self._mocked and self._driver is not None:
            await _to_the_end(self._driver.xray_off())

    async def stop(self, success: bool = True) -> None:
        """High voltage off (the bluesky ``Stoppable`` protocol)."""
        await self.xray_off()

    async def pause(self) -> None:
        """High voltage off while the run is paused (the bluesky ``Pausable`` protocol)."""
        await self.xray_off()

    async def resume(self) -> None:
        """Nothing to do: the next exposure prepares again."""


class FlatPanel(DriverDevice):
    """The flat-panel detector: ``trigger`` takes one frame of the kind ``image_key`` says (a dark without X-rays,
    a flat, or a projection exposed by the generator's trigger just before); read: ``image`` and ``image_key``, and
    on orbitct's twin the view it imaged (``true_vector``, simulation truth: 12 numbers, NaN otherwise)."""

    kind = "detector"

    def __init__(self, uri: str, name: str = "", *, frame_timeout_s: float = 20.0, **options: Any) -> None:
        with self.add_children_as_readables():
            self.image, self._set_image = soft_signal_r_and_setter(np.ndarray)
            self.image_key = soft_signal_rw(int, int(ImageKey.PROJECTION))
            self.true_vector, self._set_truth = soft_signal_r_and_setter(Array1D[np.float64], np.full(12, np.nan))
        self.frame_timeout_s = frame_timeout_s
        self._shape: tuple[int, int] = (int(options.get("rows", 0) or 0), int(options.get("cols", 0) or 0))
        super().__init__(uri, name, **options)

    async def connect(
        self, mock: bool | DeviceMock[Any] = False, timeout: float = DEFAULT_TIMEOUT, force_reconnect: bool = False
    ) -> None:
        """Connect, and (not in mock mode) arm the panel for frames triggered by the generator."""
        await super().connect(mock=mock, timeout=timeout, force_reconnect=force_reconnect)
        if not self._mocked:
            self._shape = self.driver.shape

    @AsyncStatus.wrap
    async def trigger(self) -> None:
        """Take one frame of the kind ``image_key`` holds."""
        key = ImageKey(int(await self.image_key.get_value()))
        if self._mocked:
            self._set_image(np.zeros(self._shape, dtype=np.uint16))
            return
        det = self.driver
        if key == ImageKey.DARK:
            frame = (await asyncio.wait_for(det.acquire_dark(1), self.frame_timeout_s))[0]
        elif key == ImageKey.FLAT:
            frame = (await asyncio.wait_for(det.acquire_flat(1), self.frame_timeout_s))[0]
        else:
            frame = await det.read_frame(self.frame_timeout_s)
        self._set_image(np.asarray(frame.data))
        truth = frame.meta.get("truth_vectors") if key == ImageKey.PROJECTION else None
        self._set_truth(np.full(12, np.nan) if truth is None else np.asarray(truth, dtype=np.float64).reshape(12))
