"""How a rig's drivers reach their devices: a URI and driver options per device kind."""

from __future__ import annotations

from typing import Any, NamedTuple


class DeviceLink(NamedTuple):
    """How a driver reaches its device: a URI and the driver's options (twin options too, for ``sim://``)."""

    uri: str
    options: dict[str, Any]
