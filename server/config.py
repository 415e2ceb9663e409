"""The server's one configuration object: command-line flags, ``EGOPOSEVR_*`` variables and a TOML file.

Every setting has one key, spelled ``max_sessions`` in TOML, ``EGOPOSEVR_MAX_SESSIONS`` in the environment
and ``--max-sessions`` on the command line. Precedence: flags > environment > TOML file > defaults. The file
is ``--config FILE`` or ``EGOPOSEVR_CONFIG``; an unknown key in it, or any bad value anywhere, fails at
startup with a message naming the key (pydantic-settings does the merging and the validation).

>>> ServerConfig(port=0).max_sessions
16
"""

from __future__ import annotations

import contextvars
import os
import ssl
import tomllib
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import Field, SecretStr, ValidationError, field_validator, model_validator
from pydantic_settings import (
    BaseSettings,
    NoDecode,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
    TomlConfigSettingsSource,
)

from ..model.runtime.frames import DEFAULT_LOW_HEAD_WAIT_US, FIRST_FRAME_WAIT_US, LOW_HEAD_M
from ..protocol import DEFAULT_MAX_MESSAGE_BYTES

ENV_PREFIX = "EGOPOSEVR_"
_TOML_FILE: contextvars.ContextVar[Path | None] = contextvars.ContextVar("toml_file", default=None)


class ConfigError(ValueError):
    """A configuration that cannot start a server; the message names the key and the problem."""


class ServerConfig(BaseSettings):
    """All server settings; frozen once built."""

    model_config = SettingsConfigDict(env_prefix=ENV_PREFIX, extra="forbid", frozen=True)

    host: str = Field("127.0.0.1", description="interface to listen on (0.0.0.0: every interface)")
    port: int = Field(8765, ge=0, le=65535, description="TCP port; 0 picks a free one")
    models_dir: Path | None = Field(None, description="extra ONNX models, rescanned while running")
    bundled_models: bool = Field(True, description="serve the models shipped in the package")
    default_model: str = Field("egoposevr", description="model for sessions that ask for none")
    rescan_s: float = Field(2.0, ge=0, description="models_dir rescan period; 0 = only at startup")
    workers: int = Field(max(os.cpu_count() or 2, 1), ge=1, le=64, description="inference threads")
    ort_threads: int = Field(1, ge=1, le=64, description="onnxruntime threads per model")
    providers: str = Field(
        "cpu",
        description="onnxruntime execution providers, most preferred first (cpu, cuda, tensorrt, openvino, "
        "...); one that is not installed is an error unless a later one is listed to fall back to: cuda,cpu",
    )
    max_message_bytes: int = Field(DEFAULT_MAX_MESSAGE_BYTES, ge=1024, description="largest message accepted")
    max_sessions: int = Field(16, ge=1, description="sessions at once; more get server_full")
    max_renders_per_session: int = Field(32, ge=0, description="render clients per session")
    rate_limit_hz: float = Field(400.0, gt=0, description="messages per second per session (sustained)")
    rate_burst: int = Field(200, ge=1, description="messages a session may send at once above the rate")
    pose_queue: int = Field(4, ge=1, le=1024, description="poses buffered per client; the oldest is dropped")
    send_buffer_bytes: int = Field(
        65536,
        ge=4096,
        description="kernel send buffer per connection: bounds how stale a slow viewer's poses get",
    )
    token: SecretStr | None = Field(None, description="shared secret every hello must carry")
    ssl_certfile: Path | None = Field(
        None, description="TLS certificate chain (PEM): serve wss:// and https:// on the same port"
    )
    ssl_keyfile: Path | None = Field(
        None, description="its private key (PEM), if not in the certificate file"
    )
    origins: Annotated[tuple[str, ...], NoDecode] = Field(
        (), description="browser origins allowed (comma-separated); empty allows any"
    )
    record: Path | None = Field(None, description="folder: write each input connection's messages as .egrec")
    hello_timeout_s: float = Field(5.0, gt=0, description="time allowed between upgrade and hello")
    ping_interval_s: float = Field(20.0, gt=0, description="WebSocket keep-alive ping period")
    ping_timeout_s: float = Field(20.0, gt=0, description="close a connection whose pong is this late")
    shutdown_timeout_s: float = Field(5.0, gt=0, description="bound on a graceful stop")
    batch_window_ms: float = Field(
        0.01,  # PERFORMANCE.md: waiting longer for phase-shifted headsets cost more latency than it batched
        ge=0,
        le=11.1,
        description="cross-session batching: a ready headset job waits at most this long for other sessions' "
        "jobs on the same model to run as one fusion-net call (0: off, every job runs alone)",
    )
    max_batch: int = Field(16, ge=1, le=64, description="most sessions' jobs in one batch")
    frame_lane: bool = Field(
        True,
        description="decode + encode camera frames on a low-priority thread beside the headset jobs "
        "(off: each frame rides on the next headset job, adding its cost to that pose's latency)",
    )
    first_frame_wait_ms: float = Field(
        FIRST_FRAME_WAIT_US / 1000,
        ge=0,
        le=1000,
        description="for a model that reads the camera, a stream's first headset samples wait at most this long "
        "for its first camera frame, so that the first answer has the camera's measure of the legs (0: answered "
        "at once; PROTOCOL.md §first-frame)",
    )
    low_head_wait_ms: float = Field(
        DEFAULT_LOW_HEAD_WAIT_US / 1000,
        ge=0,
        le=2000,
        description="for a model that reads the camera, a stream whose first headset sample has the head lower than "
        f"{LOW_HEAD_M} m (seated or crouched) waits at most this long for the net's visual window of frames before "
        "its first answer, so that a seated person's legs are not first served from one frame and then re-seated "
        "(0: only the first frame is waited for; needs the frame lane; PROTOCOL.md §first-frame)",
    )
    log_level: Literal["debug", "info", "warning", "error"] = "info"

    @model_validator(mode="after")
    def _tls_files_exist(self) -> ServerConfig:
        if self.ssl_keyfile is not None and self.ssl_certfile is None:
            raise ValueError("ssl_keyfile needs ssl_certfile")
        for path in (self.ssl_certfile, self.ssl_keyfile):
            if path is not None and not path.is_file():
                raise ValueError(f"{path} does not exist")
        return self

    def ssl_context(self) -> ssl.SSLContext | None:
        """The server's TLS context, or None for plain ws://. Raises ConfigError for unusable files."""
        if self.ssl_certfile is None:
            return None
        context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
        context.minimum_version = ssl.TLSVersion.TLSv1_2
        try:
            context.load_cert_chain(self.ssl_certfile, self.ssl_keyfile)
        except (ssl.SSLError, OSError) as exc:
            raise ConfigError(
                f"ssl_certfile/ssl_keyfile: cannot load the certificate and key ({exc})"
            ) from None
        return context

    @field_validator("providers")
    @classmethod
    def _known_providers(cls, value: str) -> str:
        from ..model.runtime.loading import ProviderError, resolve_providers

        try:
            resolve_providers(value)
        except ProviderError as exc:
            raise ValueError(str(exc)) from None
        return value

    @field_validator("origins", mode="before")
    @classmethod
    def _split_origins(cls, value: Any) -> Any:
        if isinstance(value, str):
            return tuple(o.strip() for o in value.split(",") if o.strip())
        return value

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        toml = TomlConfigSettingsSource(settings_cls, toml_file=_TOML_FILE.get())
        return init_settings, env_settings, toml


def load_config(flags: dict[str, Any] | None = None, config_file: str | Path | None = None) -> ServerConfig:
    """Merge flags (keys as above; None values are ignored), the environment and the TOML file."""
    flags = {k: v for k, v in (flags or {}).items() if v is not None}
    path = config_file or os.environ.get(f"{ENV_PREFIX}CONFIG")
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise ConfigError(f"config file {path} does not exist")
        try:
            tomllib.loads(path.read_text())
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise ConfigError(f"config file {path} is not valid TOML: {exc}") from None
    token = _TOML_FILE.set(path)
    try:
        return ServerConfig(**flags)
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(map(str, e['loc'])) or '?'}: {e['msg']}" for e in exc.errors())
        raise ConfigError(f"bad server configuration: {problems}") from None
    finally:
        _TOML_FILE.reset(token)
