"""The console's tests use the service's fixtures (a service on the twins with one token per role)."""

from tests.app.service.conftest import api, make_api, shared_api  # noqa: F401 - pytest finds fixtures by name
