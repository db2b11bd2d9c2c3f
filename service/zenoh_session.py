"""Opening zenoh sessions from configuration."""

from __future__ import annotations

import json
import re
from pathlib import Path

import zenoh

from service.config import ZenohSettings


def zenoh_config(settings: ZenohSettings, role: str, embedded: bool = False) -> zenoh.Config:
    """A zenoh Config for ``role``: "server" listens on ``listen``; "client" connects to ``connect``
    (or, when that is empty, to the server's ``listen`` endpoints). ``embedded``: no endpoints at all."""
    if settings.config_file is not None:
        return _from_file(settings, role, embedded)
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(settings.mode))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(settings.multicast_scouting))
    if embedded:
        conf.insert_json5("listen/endpoints", "[]")
        return conf
    if role == "server" and settings.mode != "client":
        conf.insert_json5("listen/endpoints", json.dumps(settings.listen))
        if settings.connect:
            conf.insert_json5("connect/endpoints", json.dumps(settings.connect))
    elif role == "server":  # a client-mode service connects to a router
        conf.insert_json5("connect/endpoints", json.dumps(settings.connect or settings.listen))
    else:
        conf.insert_json5("listen/endpoints", "[]")
        conf.insert_json5("connect/endpoints", json.dumps(settings.connect or settings.listen))
    return conf


def _from_file(settings: ZenohSettings, role: str, embedded: bool) -> zenoh.Config:
    """The native configuration file, with only the transport fields set explicitly here on top of it."""
    assert settings.config_file is not None
    path = Path(settings.config_file)
    if not path.is_file():
        raise ConnectionError(f"zenoh configuration file not found: {path}")
    try:
        conf = zenoh.Config.from_file(str(path))
    except zenoh.ZError as exc:
        raise ConnectionError(f"zenoh configuration file {path} is invalid: {_one_line(exc)}") from None
    explicit = settings.model_fields_set
    if "mode" in explicit:
        conf.insert_json5("mode", json.dumps(settings.mode))
    if embedded:
        conf.insert_json5("listen/endpoints", "[]")
    elif "listen" in explicit and role == "server":
        conf.insert_json5("listen/endpoints", json.dumps(settings.listen))
    if "connect" in explicit and not embedded:
        conf.insert_json5("connect/endpoints", json.dumps(settings.connect))
    return conf


def _one_line(exc: Exception) -> str:
    return re.sub(r"\s+at\s+\S+\.rs:\d+\.?", "", " ".join(str(exc).split()))


MESSAGE_OVERHEAD_BYTES = 64 * 1024
"""Room above the largest frame for zenoh's own framing when bounding the messages a session takes."""


def open_session(
    settings: ZenohSettings, role: str, embedded: bool = False, max_message_bytes: int | None = None
) -> zenoh.Session:
    """Open a session; raises ConnectionError with one clear line when zenoh refuses.

    ``max_message_bytes``: larger messages are dropped by zenoh's transport before they are reassembled into
    memory (``transport/link/rx/max_message_size``; the link stays up): 60 MB of junk every 0.1 s otherwise
    cost the service 200 MB of RSS before its own size check could refuse them."""
    conf = zenoh_config(settings, role, embedded)
    if max_message_bytes is not None:
        limit = max_message_bytes + MESSAGE_OVERHEAD_BYTES
        conf.insert_json5("transport/link/rx/max_message_size", json.dumps(limit))
    try:
        return zenoh.open(conf)
    except zenoh.ZError as exc:
        reason = _one_line(exc)
        endpoints = settings.connect or settings.listen
        raise ConnectionError(f"cannot open zenoh session (mode {settings.mode}, {endpoints}): {reason}") from None
