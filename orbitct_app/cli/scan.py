"""``orbitct scan``: run an orbit on the bench (or its twins) into a scan file; ``orbitct scan repair FILE``."""

from __future__ import annotations

import signal
from collections import Counter
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click
import yaml

from acquire.options import ScanOptions
from orbitct.livewarnings import ABORT_KINDS
from orbitct_app.cli.failure import fail
from orbitct_app.cli.model_options import model_from, options_from
from orbitct_app.cli.progress import ProgressBar
from orbitct_app.live_options import LiveCalibrationOptions

if TYPE_CHECKING:
    from acquire.runner import ScanRequest
    from orbitct_app.live_calibration import LiveCalibrationSubscriber


#: the options whose flag is not the field's name
FLAGS = {"frame_rate_hz": "--frame-rate"}


def _parse_params(items: tuple[str, ...], flag: str) -> dict[str, object]:
    """``KEY=VALUE`` items (values read as YAML: numbers, lists) as a dict."""
    out: dict[str, object] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            fail(f"{flag} {item!r} is not KEY=VALUE", advice="write it as KEY=VALUE, e.g. amplitude_deg=8")
        out[key.strip()] = yaml.safe_load(value)
    return out


@click.group(invoke_without_command=True)
@click.option(
    "--config",
    "config_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Bench or C-arm configuration (config/bench.yaml).",
)
@options_from(ScanOptions, flags=FLAGS, exclude={"orbit_params", "error_params"})
@click.option(
    "--param",
    "-p",
    "params",
    multiple=True,
    metavar="KEY=VALUE",
    help="Orbit parameter, repeatable (e.g. -p amplitude_deg=8 -p start_deg=-180); see orbitct orbit.",
)
@click.option(
    "--error-param",
    "error_params",
    multiple=True,
    metavar="KEY=VALUE",
    help="Parameter of the custom error profile (--errors custom), repeatable (e.g. --error-param "
    "angle_noise_deg=[0.1,0,0]).",
)
@click.option("--sim", is_flag=True, help="Start the device twins in-process (nothing else needs to run).")
@click.option(
    "--bbs-from",
    "bbs_from",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    default=None,
    help="With --sim: the twins' object carries the BBs of this plan (orbitct plan bbs) instead of its own.",
)
@click.option(
    "--detector-size",
    type=click.IntRange(16, 4096),
    default=None,
    help="Square detector of this many pixels on the same panel (default: the config's).",
)
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), default=None, help="Scan file to write (.h5).")
@click.option("--overwrite", is_flag=True, help="Replace an existing output file.")
@click.option(
    "--data-dir",
    type=click.Path(file_okay=False, path_type=Path),
    envvar="ORBITCT_DATA_DIR",
    default=None,
    help="The service's data directory (or ORBITCT_DATA_DIR): refuse to scan while its emergency stop is latched.",
)
@options_from(LiveCalibrationOptions, exclude={"abort_on"})
@click.option(
    "--abort-on",
    "abort_on",
    multiple=True,
    type=click.Choice(ABORT_KINDS),
    help="Stop the scan safely on this live calibration warning (repeatable).",
)
@click.pass_context
def scan(
    ctx: click.Context,
    config_path: Path | None,
    orbit: str | None,
    frames: int | None,
    params: tuple[str, ...],
    error_params: tuple[str, ...],
    errors: str | None,
    seed: int | None,
    mode: str | None,
    sim: bool,
    bbs_from: Path | None,
    detector_size: int | None,
    frame_rate_hz: float | None,
    out: Path | None,
    overwrite: bool,
    data_dir: Path | None,
    calibrate: str | None,
    bb_diameter_mm: float | None,
    lost_frames: int | None,
    abort_on: tuple[str, ...],
) -> None:
    """Acquire a scan: orbitct scan --config config/bench.yaml --orbit sawtooth --sim --out scan.h5"""
    if ctx.invoked_subcommand is not None:
        return
    if config_path is None or out is None:
        fail("orbitct scan needs --config FILE and --out FILE", advice="see 'orbitct scan --help'")
    from acquire.errors import AcquireError, DiskSpaceError
    from acquire.priority import bench_priority
    from acquire.runner import SIGNAL_REASONS, ScanRequest, run_scan

    if data_dir is not None:
        from orbitct_app.service.safety.latch import StopLatch

        refused = StopLatch(data_dir).refusal("scans")
        if refused:
            fail(refused, "stop_latched")

    given = {"orbit": orbit, "frames": frames, "errors": errors, "seed": seed, "mode": mode}
    options = model_from(
        ScanOptions,
        {
            **given,
            "frame_rate_hz": frame_rate_hz,
            "orbit_params": _parse_params(params, "--param"),
            "error_params": _parse_params(error_params, "--error-param"),
        },
        flags=FLAGS,
    )
    req = ScanRequest(
        config=config_path if bbs_from is None else _planned_config(config_path, bbs_from, sim),
        out=out,
        **options.model_dump(),
        sim=sim,
        detector_size=detector_size,
        overwrite=overwrite,
    )
    if abort_on and calibrate != "live":
        fail("--abort-on needs --calibrate live", advice="add --calibrate live, or leave out --abort-on")
    live_options = model_from(
        LiveCalibrationOptions,
        {
            "calibrate": calibrate,
            "bb_diameter_mm": bb_diameter_mm,
            "abort_on": list(abort_on),
            "lost_frames": lost_frames,
        },
    )
    live = None
    try:
        with ProgressBar() as bar, bench_priority():
            if live_options.calibrate == "live":
                live = _live_subscriber(req, out, live_options, bar)
            res = run_scan(req, progress=bar, subscribers=[live] if live is not None else [])
    except DiskSpaceError as exc:  # refused before anything moved
        fail(str(exc), "insufficient_storage", "free some space or write the scan elsewhere", exit_status=2)
    except AcquireError as exc:
        fail(str(exc))
    except KeyboardInterrupt:
        fail(
            "scan interrupted (Ctrl-C): axes halted, X-rays off",
            "interrupted",
            f"the partial file {out} is kept, marked aborted; scan again when ready",
        )
    rate = res.n_frames / res.elapsed_s if res.elapsed_s > 0 else 0.0
    signals = {reason: 128 + int(sig) for sig, reason in SIGNAL_REASONS.items()}
    try:  # after SIGHUP the terminal may be gone: the file already says how the scan ended
        click.echo(
            f"{res.status}: {res.n_frames}/{res.n_planned} frames{_kinds(res.path)} in {res.elapsed_s:.1f} s "
            f"({rate:.1f} frames/s) -> {res.path}"
        )
    except OSError:
        pass
    if res.status != "complete":
        if res.reason in signals:
            fail(f"scan {res.status}: {res.reason}", "interrupted", exit_status=signals[res.reason])
        fail(f"scan {res.status}: {res.reason}", "action_failed", "fix what the reason names and scan again")
    if live is not None:
        _report_live(live, out)


def _kinds(path: Path) -> str:
    """`` (N projections, M darks and flats)`` as the scan file counts them (the views a calibration counts); empty
    when the file cannot say."""
    from orbitct.scanfile import ScanFile, ScanFileError

    try:
        with ScanFile(path) as sf:
            kinds = sf.count_by_kind()
    except ScanFileError:
        return ""
    return f" ({kinds['projection']} projections, {kinds['dark'] + kinds['flat']} darks and flats)"


def _planned_config(config_path: Path, plan: Path, sim: bool) -> Any:
    """The configuration at ``config_path`` whose twins image the BBs of ``plan`` (``--bbs-from``)."""
    from acquire.config import load_config
    from acquire.errors import ConfigError
    from orbitct_app.bbplan import BBPlanError, read_bb_plan

    if not sim:
        fail("--bbs-from needs --sim: real BBs are where they are taped", advice="add --sim, or leave out --bbs-from")
    try:
        cfg = load_config(config_path)
        planned_for, xyz, diameter = read_bb_plan(plan)
    except (ConfigError, BBPlanError) as exc:
        fail(str(exc))
    if planned_for not in (None, cfg.sim.phantom):
        fail(
            f"{plan} was planned for experiment {planned_for}, and {config_path} images experiment {cfg.sim.phantom}",
            advice=f"plan for experiment {cfg.sim.phantom} (orbitct plan bbs -e {cfg.sim.phantom})",
        )
    sim_cfg = cfg.sim.model_copy(update={"bbs_mm": [tuple(map(float, c)) for c in xyz], "bb_diameter_mm": diameter})
    return cfg.model_copy(update={"sim": sim_cfg})


def _live_subscriber(
    req: ScanRequest, out: Path, options: LiveCalibrationOptions, bar: ProgressBar
) -> LiveCalibrationSubscriber:
    """The live calibration subscriber, with the BB size from the option or, on the twins, their BBs."""
    from calib.errors import CalibrationError
    from orbitct_app.live_calibration import LiveCalibrationSubscriber

    diameter_mm = options.bb_diameter_mm
    if diameter_mm is None:
        if not req.sim:
            fail(
                "--calibrate live needs the size of the BBs on the object",
                advice="add --bb-diameter-mm, e.g. --bb-diameter-mm 3.17",
            )
        diameter_mm = req.resolved_config().sim.bb_diameter_mm

    try:
        return LiveCalibrationSubscriber(
            out, diameter_mm, abort_on=options.abort_on, lost_frames=options.lost_frames, progress=bar
        )
    except CalibrationError as exc:
        fail(str(exc))


def _wait_for_live(live: LiveCalibrationSubscriber, out: Path) -> None:
    """Wait for the live calibration's final solve; a signal meanwhile ends the command at once (the scan is complete
    and recorded; its geometry can be made from the file)."""

    def interrupted(signum: int, frame: object) -> None:
        name = signal.Signals(signum).name
        fail(
            f"live calibration interrupted by {name}: the scan is complete in {out}",
            "interrupted",
            f"`orbitct calibrate {out}` makes its geometry",
            exit_status=128 + signum,
        )

    previous = {sig: signal.signal(sig, interrupted) for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    try:
        while not live.wait(0.2):
            pass
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _report_live(live: LiveCalibrationSubscriber, out: Path) -> None:
    """The live calibration's outcome after a complete scan; exit 1 without a geometry, 3 when its check failed."""
    _wait_for_live(live, out)
    err, res, lc = live.error, live.result, live.live
    if err is not None or res is None or lc is None or res.quality is None:
        fail(
            f"no live geometry ({err or 'it carries no quality check'}); the scan is complete in {out}",
            "action_failed",
            f"`orbitct calibrate {out}` makes its geometry",
        )
    kinds = Counter(w.kind for w in lc.warnings)
    named = f" ({', '.join(f'{k} {n}' for k, n in sorted(kinds.items()))})" if kinds else ""
    click.echo(
        f"calibrated during the scan: {res.n_bbs} BBs, geometry written {lc.last_frame_to_geometry_s:.2f} s "
        f"after the last frame (catching up {lc.timing.get('catch_up_s', 0.0):.2f} s, final solve "
        f"{lc.timing.get('solve_s', 0.0):.2f} s); {len(lc.warnings)} warning(s) during the scan{named}; "
        f"{int(lc.timing.get('windows', 0))} sliding bundle adjustment(s) in the worker "
        f"({lc.timing.get('window_s', 0.0):.2f} s); live poses for {int(lc.timing.get('posed', 0))} of "
        f"{lc.n_projections} projections"
    )
    click.echo(res.quality.line())
    if not res.quality.passed:
        fail(
            "QUALITY CHECK FAILED: " + "; ".join(res.quality.reasons),
            "failed_quality_check",
            f"the geometry is stored, marked quality=failed; read 'When a calibration fails its quality check' in the "
            f"documentation and run `orbitct calibrate {out}` again",
        )


@scan.command("repair")
@click.argument("file", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--force",
    is_flag=True,
    help="Repair even if an acquisition seems to be writing the file still "
    "(its process alive on this machine, or the file changed in the last 30 s).",
)
def repair(file: Path, force: bool) -> None:
    """Mark a scan file left by a killed acquisition as aborted ("interrupted"), keeping every complete frame."""
    from acquire.errors import RepairError
    from acquire.repair import repair_scan

    try:
        rep = repair_scan(file, force=force)
    except RepairError as exc:
        fail(str(exc))
    click.echo(rep.summary())
