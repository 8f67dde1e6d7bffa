"""Typed service settings: defaults < settings file (YAML) < environment (``ORBITCT_``) < command line."""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any, ClassVar, Literal

from pydantic import BaseModel, Field, field_validator, model_validator
from pydantic_settings import (
    BaseSettings,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
    YamlConfigSettingsSource,
)

Role = Literal["operator", "analyst", "viewer"]


class TokenHash(BaseModel):
    """A person's sign-in: its token's SHA-256 hex digest, their roles and a name for the logs. ``role: R`` (one
    role, as files before several roles per token said it) is read as ``roles: [R]``."""

    sha256: str = Field(pattern=r"^[0-9a-f]{64}$")
    roles: list[Role] = Field(min_length=1, max_length=3)
    name: str = Field(default="", max_length=100)

    @model_validator(mode="before")
    @classmethod
    def _one_role(cls, value: Any) -> Any:
        if isinstance(value, dict) and "role" in value and "roles" not in value:
            value = {**value, "roles": [value["role"]]}
            value.pop("role")
        return value

    @property
    def role(self) -> str:
        """The roles as the console shows them: ``operator, analyst``."""
        return role_label(self.roles)


def role_label(roles: Sequence[str]) -> str:
    """Roles as the console shows them, in one line: ``operator, analyst``."""
    return ", ".join(roles)


class ServiceSettings(BaseSettings):
    """Everything ``orbitct serve`` needs; every field can come from the file, ``ORBITCT_<FIELD>`` or the CLI."""

    model_config = SettingsConfigDict(env_prefix="ORBITCT_", extra="forbid")
    settings_file: ClassVar[Path | None] = None

    bench_config: Path = Field(default=Path("config/bench.yaml"), description="bench configuration (YAML)")
    sim: bool = Field(default=False, description="start in-process device twins instead of real hardware")
    host: str = Field(default="127.0.0.1", max_length=255)
    port: int = Field(default=8000, ge=1, le=65535)
    stop_port: int | None = Field(
        default=None, ge=0, le=65535, description="the guard's own stop listener (default: port + 1; 0: any free port)"
    )
    data_dir: Path = Field(default=Path("orbitct-data"), description="scan files, job outputs, database")
    tokens_file: Path | None = Field(default=None, description="token hashes (JSON); default <data_dir>/tokens.json")
    tokens: list[TokenHash] = Field(default_factory=list, description="token hashes configured inline")
    dev_token: str | None = Field(
        default=None, min_length=16, max_length=200, description="--sim only: a fixed dev token"
    )
    max_body_bytes: int = Field(default=64 * 1024, ge=1024, le=16 * 1024 * 1024)
    max_upload_bytes: int = Field(
        default=32 * 1024 * 1024,
        ge=1024,
        le=1024 * 1024 * 1024,
        description="largest file an upload may send (a surface mesh: POST /surfaces)",
    )
    job_workers: int = Field(
        default=1,
        ge=1,
        le=64,
        description="calibration/reconstruction jobs at once (and the embedded Dask cluster's worker processes)",
    )
    dask_scheduler: str | None = Field(
        default=None,
        pattern=r"^(tcp|tls)://[^\s/:]+:\d{1,5}$",
        description="an existing Dask scheduler that runs the jobs (tcp://host:8786); "
        "default: an embedded local cluster",
    )
    cancel_grace_s: float = Field(
        default=5.0, ge=0.1, le=120.0, description="time a cancelled job gets before it is killed"
    )
    reconstruction_max_minutes: float = Field(
        default=60.0,
        gt=0.0,
        le=10080.0,
        description="a reconstruction job estimated "
        "to take longer fails at once, before any work (a request may raise it)",
    )
    pacs_nodes: dict[str, str] = Field(
        default_factory=dict,
        description="DICOM nodes the service may query, fetch "
        "runs from and send series to: name -> dicom://AE_TITLE@host:port",
    )
    pacs_calling_aet: str = Field(
        default="ORBITCT",
        min_length=1,
        max_length=16,
        pattern=r"^[ -~]*[!-~][ -~]*$",
        description="the AE title orbitct calls the nodes with",
    )
    max_scan_frames: int = Field(default=5000, ge=1, le=100_000)
    bench_nice: int = Field(
        default=-5, ge=-20, le=0, description="priority asked for the bench process (needs root or CAP_SYS_NICE)"
    )
    status_interval_s: float = Field(
        default=0.25, ge=0.01, le=10.0, description="how often scan progress goes to the DB"
    )

    @field_validator("pacs_nodes")
    @classmethod
    def _pacs_nodes(cls, nodes: dict[str, str]) -> dict[str, str]:
        from orbitct_app.pacs import PacsError, PacsNode

        for name, uri in nodes.items():
            if not re.fullmatch(r"[A-Za-z0-9_-]{1,32}", name):
                raise ValueError(f"PACS node name {name!r}: 1 to 32 letters, digits, '_' or '-'")
            try:
                PacsNode.parse(uri)
            except PacsError as exc:
                raise ValueError(str(exc)) from None
        return nodes

    @model_validator(mode="after")
    def _dev_token_only_in_sim(self) -> ServiceSettings:
        if self.dev_token is not None and not self.sim:
            raise ValueError("dev_token is allowed only with sim: true (no default token on real hardware)")
        return self

    @property
    def tokens_path(self) -> Path:
        """Where token hashes are stored."""
        return self.tokens_file if self.tokens_file is not None else self.data_dir / "tokens.json"

    @property
    def db_path(self) -> Path:
        """The SQLite database of scans and jobs."""
        return self.data_dir / "orbitct.sqlite"

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        sources: list[PydanticBaseSettingsSource] = [init_settings, env_settings]
        if cls.settings_file is not None:
            sources.append(YamlConfigSettingsSource(settings_cls, yaml_file=cls.settings_file))
        return tuple(sources)


def load_settings(settings_file: Path | None = None, **overrides: Any) -> ServiceSettings:
    """Settings from ``settings_file`` (optional YAML), the environment and ``overrides`` (None values ignored)."""
    given = {k: v for k, v in overrides.items() if v is not None}

    class _FromFile(ServiceSettings):
        pass

    _FromFile.settings_file = settings_file
    loaded = _FromFile(**given)
    return ServiceSettings.model_validate(loaded.model_dump())
