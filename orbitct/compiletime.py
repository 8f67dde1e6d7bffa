"""Time spent compiling numerical kernels (numba, first use after installation), kept out of reported timings."""

from __future__ import annotations

from types import TracebackType

from numba.core import event


class CompileClock:
    """Context manager: seconds numba spent compiling while it was active (cache loads are not compiles)."""

    def __init__(self) -> None:
        self._listener = event.TimingListener()

    @property
    def seconds(self) -> float:
        """Compilation time so far."""
        return float(self._listener.duration) if self._listener.done else 0.0

    def __enter__(self) -> CompileClock:
        event.register("numba:compile", self._listener)
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        event.unregister("numba:compile", self._listener)


__all__ = ["CompileClock"]
