"""Settings (pydantic-settings, env prefix ``FRINGESCOPE_``, optional TOML file).

Built once by the entry point and passed down explicitly; nothing below the
service layer imports settings.
"""

from __future__ import annotations

import ipaddress
import tomllib
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from app.core.limits import DEFAULT_EXPOSURE_MS, DEFAULT_LED, EXPOSURE_RANGE_MS, BitDepth, Led
from app.core.schedule import DEFAULT_SCHEDULE, schedule_by_name


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="FRINGESCOPE_", extra="forbid")

    # network
    host: str = "127.0.0.1"
    port: int = Field(8000, ge=1, le=65535)
    api_token: str | None = None
    insecure: bool = False
    cors_origins: list[str] = Field(default_factory=list)
    max_upload_mb: float = Field(200.0, gt=0)
    # a browser session (the cookie POST /api/login sets) ends after this long, s
    session_ttl_s: float = Field(12 * 3600.0, gt=0, le=30 * 86400)
    # IP addresses of reverse proxies whose X-Forwarded-Proto / X-Forwarded-For are believed
    # (TLS ends there: the session cookie is then Secure)
    trusted_proxies: list[str] = Field(default_factory=list)
    # live streams (MJPEG, WebSocket) one client address may hold at once; more get 429
    max_streams_per_client: int = Field(8, ge=1, le=1000)

    # storage
    data_dir: Path = Path("data")
    calibration_file: Path | None = None
    # what is rebuilt from parameters at every start (the simulator's traced scene geometry,
    # ~150 MB a scene, at most 4 kept): shared by data folders; None: $XDG_CACHE_HOME/fringescope
    # (~/.cache/fringescope)
    cache_dir: Path | None = None
    # a recording stops (reason in /api/status warnings) when the data disk has less free space, MB
    recording_min_free_mb: float = Field(200.0, ge=0)

    # devices: "sim" is the built-in digital twin
    camera: Literal["sim", "opencv", "genicam", "replay"] = "sim"
    projector: Literal["sim", "lightcrafter", "none"] = "sim"
    controller: Literal["sim", "serial", "none"] = "sim"
    camera_source: str = ""  # OpenCV index/URL/file, GenTL .cti path, or replay folder
    serial_port: str = ""  # device path, pyserial URL, or "usb:VID:PID[:SERIAL]"
    lightcrafter_host: str = "192.168.1.100"
    lightcrafter_port: int = 21845
    # a static tissue scene: the simulator renders it faster than the camera rate, so every
    # set is complete; "anastomosis" (breathing + moving forceps) renders below 30 frames/s here
    sim_scene: str = "intestine_flap"
    # rig preset of the simulator: "default" (the paper's rig) or "endoscope" (another sensor and
    # lens, wide triangulation angle, barrel distortion k1 = -0.25, 12-bit sensor: set
    # bit_depth = 12)
    sim_rig: Literal["default", "endoscope"] = "default"
    sim_seed: int | None = None
    sim_drop_rate: float = Field(0.0, ge=0, le=1)
    sim_timeout_rate: float = Field(0.0, ge=0, le=1)
    sim_disconnect_every_s: float = Field(0.0, ge=0)

    # acquisition
    exposure_ms: float = Field(
        DEFAULT_EXPOSURE_MS, ge=EXPOSURE_RANGE_MS[0], le=EXPOSURE_RANGE_MS[1]
    )
    led: Led = DEFAULT_LED
    bit_depth: BitDepth = 8
    rolling: bool = False
    # false-alarm rate of the motion test over the image (both modes): a map of a still scene
    # has any flagged pixel with at most this probability (app.recon.motion: the groups'
    # background spread pooled over 5 x 5 pixels, a chi-square threshold per window)
    motion_false_alarm_rate: float = Field(1e-4, gt=0, lt=0.5)
    # moved regions grow by this many pixels before they are invalidated (their rims)
    motion_grow_px: int = Field(4, ge=0, le=16)
    # gross-error tolerance, mm (0: off): a valid pixel's noise exceeds it only at rate 1e-6, so
    # pixels with σ > E/4.89 (its noise part weighed by the phasor tail, app.recon.validity step 5)
    # are UNCERTAIN, and > E/(4.89 + k) in a set where the scene moved
    # (k: the motion test's single-pixel bound; app.recon.motion.sigma_bounds, README
    # "Rolling mode and motion")
    gross_error_mm: float = Field(0.5, ge=0, le=100)
    # the camera's noise (σ and the validity rule) is measured from a live set this often, s
    # (0: the nominal SensorNoise.typical; app.service.sensor_noise)
    noise_estimate_interval_s: float = Field(30.0, ge=0, le=3600)
    # optional validity rule: pixels whose 1-σ depth noise exceeds this (mm) are UNCERTAIN;
    # benchmarks/bench_motion.py shows what it adds during motion (unset: no such rule)
    max_sigma_mm: float | None = Field(None, gt=0, le=100)
    # optional explicit modulation threshold B (codes): replaces the default noise-aware validity
    # rule (app/recon/validity.py: the schedule's order-error bound under the camera noise, and
    # its depth-σ bound unless max_sigma_mm is set); unset: the rule
    min_modulation: float | None = Field(None, ge=0, le=65535)
    autostart: bool = True
    # the fringe pattern schedule by name (app/core/schedule.py SCHEDULES): "paper-16" (the
    # paper's [1, 4, 12, 36] x 4), "geometric-12", "geometric-9", "heterodyne-9"; GET /api/schedules
    schedule: str = DEFAULT_SCHEDULE

    # viewer
    viewer: bool = True
    viewer_port: int = Field(0, ge=0, le=65535)  # 0: pick a free loopback port
    viewer_max_points: int = Field(300_000, ge=1000)

    # OpenIGTLink (3D Slicer, navigation): off unless a port is set (18944 is the convention;
    # 0 picks a free port). The protocol has no authentication: a host other than loopback
    # also needs igtl_allow_remote.
    igtl_port: int | None = Field(None, ge=0, le=65535)
    igtl_host: str = "127.0.0.1"
    igtl_allow_remote: bool = False
    igtl_max_points: int = Field(100_000, ge=1)


    @field_validator("schedule")
    @classmethod
    def _known_schedule(cls, value: str) -> str:
        schedule_by_name(value)  # ValueError naming the known ones
        return value


def load_settings(config_file: str | Path | None = None, **overrides: Any) -> Settings:
    """Settings from a TOML file (optional), then the environment, then ``overrides``.

    Environment variables win over the file; explicit overrides (command-line flags)
    win over both.
    """
    file_values: dict[str, Any] = {}
    if config_file is not None:
        path = Path(config_file)
        try:
            file_values = tomllib.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise ValueError(f"{path}: config file not found") from None
        except tomllib.TOMLDecodeError as exc:
            raise ValueError(f"{path}: invalid TOML ({exc})") from None
        file_values = dict(file_values.get("fringescope", file_values))
    env_settings = Settings()
    env_set = {k for k in Settings.model_fields if k in env_settings.model_fields_set}
    merged = {k: v for k, v in file_values.items() if k not in env_set}
    merged.update({k: v for k, v in overrides.items() if v is not None})
    return Settings(**merged)


def is_loopback(host: str) -> bool:
    """True for ``localhost`` and loopback IP literals (127.0.0.0/8, ::1): a bind address that
    only this machine reaches (the HTTP server's token rule and the OpenIGTLink port's)."""
    name = host.strip().strip("[]").lower()
    if name == "localhost":
        return True
    try:
        return ipaddress.ip_address(name).is_loopback
    except ValueError:
        return False
