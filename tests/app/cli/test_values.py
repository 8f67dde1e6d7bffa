"""What the command line refuses before any work: numbers that are not finite, negative seeds, and output files
that cannot be written — one line naming the option or the file, never a traceback."""

from __future__ import annotations

from pathlib import Path

import pytest
from click.testing import CliRunner

from orbitct_app.cli.main import cli

SIM = ["simulate", "-e", "A", "--frames", "10", "--detector-size", "32"]
PLAN = ["plan", "bbs", "-e", "A", "--frames", "10", "--detector-size", "32"]


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (SIM + ["--pitch-mm", "nan"], "'--pitch-mm': 'nan' is not a finite number"),
        (SIM + ["--pitch-mm", "inf"], "'--pitch-mm': 'inf' is not a finite number"),
        (SIM + ["--seed", "-1"], "'--seed': -1 is not in the range 0<=x<=4294967295"),
        (PLAN + ["--target-px", "nan"], "'--target-px': 'nan' is not a finite number"),
        (PLAN + ["--noise-px", "inf"], "'--noise-px': 'inf' is not a finite number"),
        (PLAN + ["--seed", "-3"], "--seed: Input should be greater than or equal to 0"),
        (["calibrate", "x.h5", "--diameter-mm", "nan"], "'--diameter-mm': 'nan' is not a finite number"),
        (["demo", "--seed", "-1"], "'--seed'"),
        (["scan", "--frame-rate", "nan"], "'--frame-rate': 'nan' is not a finite number"),
    ],
)
def test_numbers_that_are_not_finite_and_negative_seeds_are_refused(
    tmp_path: Path, args: list[str], needle: str
) -> None:
    r = CliRunner().invoke(cli, [*args, "--out", str(tmp_path / "out")] if args[0] in ("simulate", "plan") else args)
    assert r.exit_code == 2 and needle in r.output and "Traceback" not in r.output, r.output


def test_an_output_file_that_cannot_be_written_ends_the_command_in_one_line(tmp_path: Path) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    for args, out in ((SIM, blocker / "x.h5"), (PLAN + ["--bbs", "4"], blocker / "plan.json")):
        r = CliRunner().invoke(cli, [*args, "--out", str(out)])
        assert r.exit_code == 1 and r.output.startswith("error [file_error]: ") and str(blocker) in r.output, (
            r.output
        )  # it or its folder
        assert r.output.count("\n") == 1 and "Traceback" not in r.output, r.output


def test_help_shows_no_range_for_an_unbounded_number() -> None:
    """``--diameter-mm`` and the like have no bounds: their help had read ``[x<=None]``."""
    for command in (
        ["calibrate", "--help"],
        ["reconstruct", "--help"],
        ["plan", "bbs", "--help"],
        ["twin", "carm", "--help"],
    ):
        r = CliRunner().invoke(cli, command, terminal_width=200)
        assert r.exit_code == 0 and "None]" not in r.output, r.output
    plan_help = CliRunner().invoke(cli, ["plan", "bbs", "--help"], terminal_width=200).output
    assert "[default: 0.1; >0.0; <=5.0]" in plan_help  # --noise-px is bounded: its range is shown
