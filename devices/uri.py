"""Device endpoints as URIs: ``sim://``, ``tcp://host:port``, ``serial:///dev/ttyUSB0?baud=115200``."""

from __future__ import annotations

import math
from collections.abc import Set as AbstractSet
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import parse_qsl, urlsplit

from devices.errors import UriError

SCHEMES = ("sim", "tcp", "serial", "modbus", "folder")


@dataclass(frozen=True)
class Endpoint:
    """A parsed device URI."""

    scheme: str
    host: str = ""
    port: int | None = None
    path: str = ""
    params: dict[str, str] = field(default_factory=dict)

    def __str__(self) -> str:
        q = "&".join(f"{k}={v}" for k, v in self.params.items())
        base = {
            "sim": f"sim://{self.host}",
            "tcp": f"tcp://{self.host}:{self.port}",
            "modbus": f"modbus://{self.host}:{self.port}",
        }.get(self.scheme, f"{self.scheme}://{self.path}")
        return base + (f"?{q}" if q else "")


def parse_uri(uri: str, *, default_port: int | None = None) -> Endpoint:
    """Parse and check a device URI; raises :class:`UriError` naming what is allowed."""
    parts = urlsplit(uri)
    scheme = parts.scheme.lower()
    if scheme not in SCHEMES:
        raise UriError(f"device URI {uri!r}: scheme must be one of {', '.join(s + '://' for s in SCHEMES)}")
    params = dict(parse_qsl(parts.query))
    if scheme == "sim":
        return Endpoint("sim", host=parts.netloc, params=params)
    if scheme in ("tcp", "modbus"):
        if not parts.hostname:
            raise UriError(f"device URI {uri!r}: {scheme}:// needs a host, e.g. {scheme}://127.0.0.1:50000")
        try:
            port = parts.port or default_port
        except ValueError:
            raise UriError(f"device URI {uri!r}: port must be an integer 1..65535") from None
        if port is None:
            raise UriError(f"device URI {uri!r}: {scheme}:// needs a port, e.g. {scheme}://{parts.hostname}:50000")
        return Endpoint(scheme, host=parts.hostname, port=port, params=params)
    path = parts.path or parts.netloc
    if not path:
        raise UriError(f"device URI {uri!r}: {scheme}:// needs a path, e.g. serial:///dev/ttyUSB0?baud=115200")
    if scheme == "serial" and "baud" in params and not params["baud"].isdigit():
        raise UriError(f"device URI {uri!r}: baud must be an integer, got {params['baud']!r}")
    return Endpoint(scheme, path=path, params=params)


def checked_options(params: dict[str, Any], allowed: AbstractSet[str], what: str) -> dict[str, Any]:
    """``params`` (URI query and keyword options) if every name is allowed; UriError naming the allowed ones."""
    unknown = sorted(set(params) - allowed)
    if unknown:
        raise UriError(f"{what}: unknown option(s) {', '.join(unknown)}; allowed: {', '.join(sorted(allowed))}")
    return params


def option_number(value: Any, cast: type = float) -> Any:
    """An option value as a number (URI query values arrive as text); UriError when it is not one."""
    try:
        number = cast(value)
    except (TypeError, ValueError):
        raise UriError(f"option value {value!r} is not a number") from None
    if not math.isfinite(number):
        raise UriError(f"option value {value!r} is not a finite number")
    return number


def option_value(value: str) -> Any:
    """A URI query value as a bool, int or float where it looks like one, else the text."""
    low = value.lower()
    if low in ("true", "yes", "on"):
        return True
    if low in ("false", "no", "off"):
        return False
    for cast in (int, float):
        try:
            number = cast(value)
        except ValueError:
            continue
        if not math.isfinite(number):
            raise UriError(f"option value {value!r} is not a finite number")
        return number
    return value
