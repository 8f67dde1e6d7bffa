"""``orbitct serve`` (the REST service) and ``orbitct token create|list|revoke`` (bearer tokens stored as hashes)."""

from __future__ import annotations

import contextlib
import logging
import signal
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import click
import uvicorn
from pydantic import ValidationError

from orbitct_app.cli.failure import Failure


class SignalAwareServer(uvicorn.Server):
    """uvicorn's server that also shuts down gracefully on SIGHUP and tells the service which signal stopped it."""

    def __init__(self, config: uvicorn.Config, service: Any) -> None:
        super().__init__(config)
        self.service = service

    @contextlib.contextmanager
    def capture_signals(self) -> Iterator[None]:
        if threading.current_thread() is not threading.main_thread():
            with super().capture_signals():
                yield
            return
        previous = signal.signal(signal.SIGHUP, self.handle_exit)  # a closed terminal stops cleanly too
        try:
            with super().capture_signals():
                yield
        finally:
            signal.signal(signal.SIGHUP, previous)

    def handle_exit(self, sig: int, frame: Any) -> None:
        from orbitct_app.service.rig import SERVICE_STOPPED

        self.service.stop_reason = f"{SERVICE_STOPPED} ({signal.Signals(sig).name})"
        super().handle_exit(sig, frame)


def _settings(**kwargs: object):
    from orbitct_app.service.core.settings import load_settings

    settings_file = kwargs.pop("settings_file", None)
    try:
        return load_settings(settings_file, **kwargs)  # type: ignore[arg-type]
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(map(str, e['loc'])) or 'settings'}: {e['msg']}" for e in exc.errors())
        raise click.UsageError(f"invalid service settings: {problems}") from None


def _check_port(host: str, port: int, option: str) -> None:
    """Refuse, before announcing anything, a port that another program listens on."""
    import socket

    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host, port))
        except OSError as exc:
            raise Failure(
                f"cannot listen on {host}:{port} ({exc.strerror})",
                "unavailable",
                f"another program (another orbitct serve?) uses it: choose another {option}",
            ) from None


def _default_sim_config(data_dir: Path) -> Path:
    """The built-in bench's configuration, written to the data directory for a simulated bench given none."""
    import yaml

    from acquire.config import BenchConfig

    path = data_dir / "bench-defaults.yaml"
    data_dir.mkdir(parents=True, exist_ok=True)
    path.write_text(
        "# The built-in simulated bench (orbitct serve --sim without --config); rewritten at every start.\n"
        + yaml.safe_dump(BenchConfig().model_dump(mode="json"), sort_keys=False),
        encoding="utf-8",
    )
    click.echo(f"no bench configuration given: the built-in simulated bench ({path})", err=True)
    return path


@click.command()
@click.option(
    "--config",
    "bench_config",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="bench configuration (YAML), e.g. config/bench.yaml",
)
@click.option("--sim", is_flag=True, default=None, help="start in-process device twins; prints a development token")
@click.option("--host", default=None, help="address to listen on (default 127.0.0.1)")
@click.option("--port", type=int, default=None, help="port (default 8000)")
@click.option(
    "--stop-port",
    type=int,
    default=None,
    help="port of the emergency-stop listener, a process of its own (default: port + 1; 0: any free port)",
)
@click.option(
    "--data-dir",
    type=click.Path(file_okay=False, path_type=Path),
    default=None,
    help="scan files, job outputs, database and tokens (default ./orbitct-data)",
)
@click.option(
    "--settings",
    "settings_file",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    default=None,
    help="service settings (YAML); environment ORBITCT_* and these options override it",
)
@click.option("--log-level", type=click.Choice(["debug", "info", "warning", "error"]), default="info")
def serve(
    bench_config: Path | None,
    sim: bool | None,
    host: str | None,
    port: int | None,
    stop_port: int | None,
    data_dir: Path | None,
    settings_file: Path | None,
    log_level: str,
) -> None:
    """Run the REST service (scans, calibration, reconstruction, emergency stop) with uvicorn."""
    from orbitct_app.service.app import create_app

    settings = _settings(
        settings_file=settings_file,
        bench_config=bench_config,
        sim=sim,
        host=host,
        port=port,
        stop_port=stop_port,
        data_dir=data_dir,
    )
    logging.basicConfig(level=log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    default_config = type(settings).model_fields["bench_config"].default
    if settings.sim and settings.bench_config == default_config and not settings.bench_config.is_file():
        settings = settings.model_copy(update={"bench_config": _default_sim_config(settings.data_dir)})
    if not settings.bench_config.is_file():
        raise click.UsageError(f"bench configuration {settings.bench_config} does not exist")
    _check_port(settings.host, settings.port, "--port")
    stop_port = settings.port + 1 if settings.stop_port is None else settings.stop_port
    if stop_port:
        _check_port(settings.host, stop_port, "--stop-port")
    from orbitct_app.service.core.datadir import DataDirBusy

    try:
        app = create_app(settings)
    except DataDirBusy as exc:
        raise click.ClickException(str(exc)) from None
    except Exception as exc:
        from orbitct_app.service.core.errors import disk_full

        if not disk_full(exc):
            raise
        from orbitct.diskspace import format_bytes, free_bytes

        raise Failure(
            f"cannot start: the disk of the data directory {settings.data_dir} is full "
            f"({format_bytes(free_bytes(settings.data_dir))} free) and the service cannot create its database there",
            "insufficient_storage",
            "free some space or choose another --data-dir",
        ) from None
    service = app.state.service
    if service.dev_token is not None:
        click.echo(f"--sim development token (all roles, valid until the service stops):\n  {service.dev_token}")
    click.echo(f"orbitct service on http://{settings.host}:{settings.port}  (API docs: /docs)")
    config = uvicorn.Config(app, host=settings.host, port=settings.port, log_level=log_level, access_log=False)
    try:
        SignalAwareServer(config, service).run()
    except KeyboardInterrupt:  # Ctrl-C: the service has shut down cleanly (scan aborted, devices stopped)
        click.echo("orbitct service stopped (Ctrl-C)")


@click.group()
def token() -> None:
    """Manage bearer tokens (only their SHA-256 hashes are stored)."""


def _token_file_options(fn):
    fn = click.option(
        "--tokens-file",
        type=click.Path(dir_okay=False, path_type=Path),
        default=None,
        help="tokens file (default <data-dir>/tokens.json)",
    )(fn)
    return click.option(
        "--data-dir",
        type=click.Path(file_okay=False, path_type=Path),
        default=None,
        help="service data directory holding tokens.json (default ./orbitct-data)",
    )(fn)


@token.command("create")
@click.option(
    "--role",
    "roles",
    type=click.Choice(["operator", "analyst", "viewer"]),
    required=True,
    multiple=True,
    help="operator: motion, X-rays, scans, people; analyst: calibration, reconstruction, BB plans; viewer: read "
    "only. Repeat it for a person with several roles (--role operator --role analyst).",
)
@click.option("--name", default="", help="a unique name, shown in logs and by `token list` (default <roles>-<n>)")
@_token_file_options
def create(roles: tuple[str, ...], name: str, data_dir: Path | None, tokens_file: Path | None) -> None:
    """Create a person's token with their ROLEs, store its hash, print the token once."""
    from orbitct_app.service.core.auth import TokenFileError, create_token

    settings = _settings(data_dir=data_dir, tokens_file=tokens_file)
    try:
        value = create_token(settings.tokens_path, list(roles), name)  # type: ignore[arg-type]
    except TokenFileError as exc:
        raise click.ClickException(str(exc)) from None
    click.echo(value)
    click.echo(
        f"(roles {', '.join(dict.fromkeys(roles))}; hash stored in {settings.tokens_path}; this token is not shown "
        "again)",
        err=True,
    )


@token.command("list")
@_token_file_options
def list_tokens(data_dir: Path | None, tokens_file: Path | None) -> None:
    """List the stored tokens: name, role and the start of the hash (tokens themselves are never stored)."""
    from orbitct_app.service.core.auth import TokenFileError, read_token_file

    settings = _settings(data_dir=data_dir, tokens_file=tokens_file)
    try:
        entries = read_token_file(settings.tokens_path)
    except TokenFileError as exc:
        raise click.ClickException(str(exc)) from None
    if not entries:
        click.echo(f"no tokens in {settings.tokens_path}; make one with `orbitct token create --role operator`")
        return
    width = max(len(e.name) for e in entries)
    roles = max(len(e.role) for e in entries)
    click.echo(f"{'name':<{width}}  {'roles':<{roles}}  hash")
    for e in entries:
        click.echo(f"{e.name:<{width}}  {e.role:<{roles}}  {e.sha256[:12]}")
    click.echo(
        f"({len(entries)} in {settings.tokens_path}; tokens in the service settings file are not listed)", err=True
    )


@token.command("revoke")
@click.argument("name_or_hash")
@_token_file_options
def revoke(name_or_hash: str, data_dir: Path | None, tokens_file: Path | None) -> None:
    """Revoke a token by its NAME (or the start of its hash, as `token list` shows it); a running service stops
    accepting it at the next request."""
    from orbitct_app.service.core.auth import TokenFileError, revoke_token

    settings = _settings(data_dir=data_dir, tokens_file=tokens_file)
    try:
        gone = revoke_token(settings.tokens_path, name_or_hash)
    except TokenFileError as exc:
        raise click.ClickException(str(exc)) from None
    click.echo(f"revoked {gone.name} ({gone.role}, hash {gone.sha256[:12]})")
