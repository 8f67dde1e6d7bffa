"""Image keys of scan-file frames (the NXtomo convention): the one definition every package uses."""

from __future__ import annotations

from enum import IntEnum


class ImageKey(IntEnum):
    """What a frame shows: ``/frames/image_key`` holds these numbers."""

    PROJECTION = 0
    FLAT = 1
    DARK = 2
    INVALID = 3

    @property
    def label(self) -> str:
        """Lower-case name (``projection``, ``flat``, ``dark``, ``invalid``)."""
        return self.name.lower()

    @classmethod
    def parse(cls, value: int | str | ImageKey) -> ImageKey:
        """An image key from its number or its label; ValueError naming the allowed ones."""
        try:
            return cls[value.upper()] if isinstance(value, str) else cls(int(value))
        except (KeyError, ValueError):
            allowed = ", ".join(f"{k.value} {k.label}" for k in cls)
            raise ValueError(f"image key must be one of {allowed}; got {value!r}") from None
