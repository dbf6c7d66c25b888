"""The bridge's Zenoh session: its config, and whether that config controls who may command.

The bridge takes commands only where Zenoh itself decides who reaches them: access control
rules, user/password authentication or TLS with client certificates, read from the session's
config (the ``config_file``, then the section's keys over it). Without any of them a bridge
with commands refuses to start, unless ``allow_anyone`` says a lab does without. The check
reads the bridge's own Zenoh config only: through a router, the router's config is the
boundary.
"""

from __future__ import annotations

import json
import logging
from typing import Any

from ..errors import ConfigError, ConfigIssue
from ..files import read_regular_text
from .options import UNCONTROLLED, ZenohBridgeSection

log = logging.getLogger(__name__)


def session_config(section: ZenohBridgeSection) -> Any:
    """The session's ``zenoh.Config``: the file if one is named, then the section's keys over it."""
    import zenoh

    if section.config_file:  # read here, a regular file only: zenoh's own reader would wait on a FIFO
        text = read_regular_text(section.config_file, "bridge.zenoh.config_file")
        try:
            config = zenoh.Config.from_json5(text)
        except Exception as exc:  # zenoh's own error type
            raise ConfigError(
                [ConfigIssue("bridge.zenoh.config_file", f"{section.config_file}: not a Zenoh config: {exc}")]
            ) from None
    else:
        config = zenoh.Config()
    config.insert_json5("mode", json.dumps(section.mode))
    config.insert_json5("listen/endpoints", json.dumps(section.listen))
    config.insert_json5("connect/endpoints", json.dumps(section.connect))
    config.insert_json5("scouting/multicast/enabled", json.dumps(section.multicast_scouting))
    return config


def _get(config: Any, key: str) -> Any:
    return json.loads(config.get_json(key))


def access_controlled_by(config: Any) -> str | None:
    """What in this config decides who reaches the session, or None."""
    acl = _get(config, "access_control") or {}
    if acl.get("enabled") and acl.get("rules") and acl.get("policies"):
        return "access_control"
    usrpwd = _get(config, "transport/auth/usrpwd") or {}
    if usrpwd.get("dictionary_file"):
        return "user/password authentication"
    tls = _get(config, "transport/link/tls") or {}
    listen = _get(config, "listen/endpoints")
    if isinstance(listen, dict):  # zenoh's default: a list per mode
        listen = listen.get(_get(config, "mode") or "peer", [])
    if tls.get("enable_mtls") and listen and all(e.startswith(("tls/", "quic/")) for e in listen):
        return "TLS client certificates"
    return None


def check_access(section: ZenohBridgeSection, config: Any) -> str | None:
    """Refuse commands that anyone could send (``ConfigError`` on ``bridge.zenoh.commands``);
    return what controls access (None: no command, or ``allow_anyone``)."""
    if not section.commands:
        return None
    means = access_controlled_by(config)
    if means is None and not section.allow_anyone:
        raise ConfigError([ConfigIssue("bridge.zenoh.commands", UNCONTROLLED)])
    return means


def check_section(section: ZenohBridgeSection) -> None:
    """The access check before a run (the CLI's exit 2): reads the config file with zenoh."""
    check_access(section, session_config(section))
