"""Errors raised while building orbits."""


class OrbitError(ValueError):
    """An orbit name or parameter that is not allowed; the message says what is allowed."""
