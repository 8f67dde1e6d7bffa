"""GCS 2.0 framing, reply parsing and the error-code table (no sockets)."""

from __future__ import annotations

import pytest

from devices.errors import (
    ControllerError,
    NotReferencedError,
    OutOfLimitsError,
    ProtocolError,
)
from devices.gcs.errors import GCS_ERRORS, controller_error
from devices.gcs.framing import (
    encode_command,
    format_command,
    join_reply,
    parse_axis_values,
    reply_complete,
    split_reply,
)
from devices.twins.gcs.server import split_commands
from devices.twins.runtime import garble


def test_single_character_commands_have_no_linefeed() -> None:
    assert encode_command("#5") == b"\x05"
    assert encode_command("#7") == b"\x07"
    assert encode_command("#24") == b"\x18"
    assert encode_command("POS? X") == b"POS? X\n"


def test_multiline_reply_framing_round_trip() -> None:
    raw = join_reply(["X=1.000000", "Y=-2.500000"])
    assert raw == b"X=1.000000 \nY=-2.500000\n"
    assert not reply_complete(b"X=1.000000 \n")
    assert reply_complete(raw)
    assert split_reply(raw) == ["X=1.000000", "Y=-2.500000"]


def test_eight_bit_text_survives() -> None:
    assert split_reply(join_reply(["\xb1"])) == ["\xb1"]
    assert join_reply(["\xb0"]) == b"\xb0\n"


def test_missing_continuation_space_is_a_protocol_error() -> None:
    with pytest.raises(ProtocolError):
        split_reply(b"X=1\nY=2\n")


def test_axis_values_and_garbled_lines() -> None:
    assert parse_axis_values(["X=1.5", "1=-3"]) == {"X": 1.5, "1": -3.0}
    with pytest.raises(ProtocolError, match="not a number"):
        parse_axis_values(["X=1.2.3"], "POS?")
    with pytest.raises(ProtocolError, match="POS"):
        reply = join_reply(["X=1", "Y=2"])
        parse_axis_values(split_reply(garble(reply, 0, len(reply) - 1)), "POS?")  # the twin keeps the final LF


def test_format_command() -> None:
    assert format_command("MOV", {"X": 1, "U": -0.5}) == "MOV X 1.000000 U -0.500000"
    assert format_command("SVO", {"1": True}) == "SVO 1 1"
    assert format_command("FRF", ["X", "Y"]) == "FRF X Y"


def test_twin_splits_lines_and_single_characters() -> None:
    cmds, rest = split_commands(b"\x05MOV X 1\nERR?\n\x18POS")
    assert cmds == ["#5", "MOV X 1", "ERR?", "#24"]
    assert rest == b"POS"


def test_error_table_matches_pi() -> None:
    from pipython.pidevice import gcserror

    for code in (1, 2, 5, 7, 10, 15, 17, 23, 24, 89, 93):
        assert str(gcserror.translate_error(code)).startswith(GCS_ERRORS[code])


def test_named_exceptions_for_codes() -> None:
    e7, e5, e10 = controller_error(7, "MOV X 60"), controller_error(5, "MOV X 1"), controller_error(10)
    assert isinstance(e7, OutOfLimitsError) and isinstance(e7, ControllerError) and e7.code == 7
    assert "MOV X 60" in str(e7) and "out of limits" in str(e7)
    assert isinstance(e5, NotReferencedError) and e5.code == 5
    assert type(e10) is ControllerError and e10.text == "Controller was stopped by command"
    assert "999" in str(controller_error(999))
