"""What a stop request says: its reason, from whatever body it has (a stop is never refused for its body)."""

from __future__ import annotations

import json

MAX_REASON = 500  # characters of a reason kept with the latch


def stop_reason(raw: bytes) -> tuple[str, str]:
    """The stop's reason from a body (``{"reason": "..."}`` JSON, or nothing), and what was wrong with the body ('' when
    nothing was)."""
    if not raw.strip():
        return "", ""
    try:
        body = json.loads(raw)
    except ValueError:
        return "", 'the body was not JSON ({"reason": "..."} or nothing)'
    reason = body.get("reason", "") if isinstance(body, dict) else None
    if not isinstance(reason, str):
        return "", "the reason was not text"
    cut = f"the reason was cut to {MAX_REASON} characters" if len(reason) > MAX_REASON else ""
    return reason[:MAX_REASON], cut
