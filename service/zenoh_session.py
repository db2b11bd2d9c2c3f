"""Opening zenoh sessions from configuration."""

from __future__ import annotations

import json
import re

import zenoh

from service.config import ZenohSettings


def zenoh_config(settings: ZenohSettings, role: str, embedded: bool = False) -> zenoh.Config:
    """A zenoh Config for ``role``: "server" listens on ``listen``; "client" connects to ``connect``
    (or, when that is empty, to the server's ``listen`` endpoints). ``embedded``: no endpoints at all."""
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


def open_session(settings: ZenohSettings, role: str, embedded: bool = False) -> zenoh.Session:
    """Open a session; raises ConnectionError with one clear line when zenoh refuses."""
    try:
        return zenoh.open(zenoh_config(settings, role, embedded))
    except zenoh.ZError as exc:
        reason = re.sub(r"\s+at\s+\S+\.rs:\d+\.?", "", " ".join(str(exc).split()))
        endpoints = settings.connect or settings.listen
        raise ConnectionError(f"cannot open zenoh session (mode {settings.mode}, {endpoints}): {reason}") from None
