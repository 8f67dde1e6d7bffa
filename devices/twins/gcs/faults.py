"""Faults a GCS twin injects on request: latency, dropped connection, garbled reply, controller error, stuck axis."""

from __future__ import annotations

import threading
from dataclasses import dataclass, field


@dataclass
class Faults:
    """Pending faults; the server and controller consume them as commands arrive (thread-safe)."""

    latency_s: float = 0.0
    drop_next: int = 0
    drop_executes: bool = True
    drop_command: str = ""  # drop only at this command (e.g. 'MOV'); empty: at any command
    garble_next: int = 0
    errors: dict[str, list[int]] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def add_error(self, code: int, command: str = "MOV", times: int = 1) -> None:
        """Make the next ``times`` ``command`` commands fail with ``code`` (not executed)."""
        with self.lock:
            self.errors.setdefault(command.upper(), []).extend([int(code)] * times)

    def take_error(self, command: str) -> int:
        """The injected code for this command, if any (consumed)."""
        with self.lock:
            codes = self.errors.get(command.upper())
            return codes.pop(0) if codes else 0

    def take_drop(self, command: str = "") -> bool:
        """Whether to drop the connection at this command (consumed)."""
        with self.lock:
            name = command.split(" ", 1)[0].upper()
            if self.drop_next > 0 and (not self.drop_command or self.drop_command.upper() == name):
                self.drop_next -= 1
                return True
            return False

    def take_garble(self) -> bool:
        """Whether to garble this reply (consumed)."""
        with self.lock:
            if self.garble_next > 0:
                self.garble_next -= 1
                return True
            return False

    def clear(self) -> None:
        """Remove every pending fault."""
        with self.lock:
            self.latency_s, self.drop_next, self.garble_next, self.drop_command = 0.0, 0, 0, ""
            self.errors.clear()
