"""PI GCS 2.0: wire framing, error codes, transports (TCP, serial) and an asyncio client."""

from devices.gcs.client import GcsClient
from devices.gcs.errors import GCS_ERRORS, GcsNotReferencedError, GcsOutOfLimitsError, controller_error, error_text

__all__ = ["GCS_ERRORS", "GcsClient", "GcsNotReferencedError", "GcsOutOfLimitsError", "controller_error", "error_text"]
