"""How a rig's drivers reach their devices: a URI and driver options per device kind."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, NamedTuple

from devices.uri import parse_uri


class DeviceLink(NamedTuple):
    """How a driver reaches its device: a URI and the driver's options (twin options too, for ``sim://``)."""

    uri: str
    options: dict[str, Any]


def configured_link(uri: str, driver_options: Mapping[str, Any], twin_options: Mapping[str, Any]) -> DeviceLink:
    """The link to a configured ``uri``; a ``sim://`` twin there also takes ``twin_options`` (what the configuration
    says of the device it stands in for: panel size, distances, phantom) where the URI's query leaves them open,
    so that a twin in a real bench's configuration delivers what the rest of the configuration expects."""
    options = dict(driver_options)
    endpoint = parse_uri(uri)
    if endpoint.scheme == "sim":
        options = {**{k: v for k, v in twin_options.items() if k not in endpoint.params}, **options}
    return DeviceLink(uri, options)
