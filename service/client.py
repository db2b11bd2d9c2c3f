"""Querying a running service over zenoh and printing the replies."""

from __future__ import annotations

import json
import logging
import queue
import time
from dataclasses import dataclass
from typing import Any

import zenoh
from rich.console import Console
from rich.table import Table
from rich.text import Text

from service.config import Settings
from service.zenoh_session import open_session

log = logging.getLogger(__name__)

GRACE_S = 0.25  # after the first reply: how long other replies (another service, a rogue peer) may still come
RETRY_S = 0.1  # a query that ended without a reply (routes not known yet) is sent again after this pause


@dataclass(frozen=True)
class Answer:
    """One reply: its JSON object (None for an error or a body that is not a JSON object), the error text, and
    who sent it (the reply's ``service_id``, else the replying zenoh session's id)."""

    body: dict[str, Any] | None
    error: str
    service_id: str


def query(settings: Settings, what: str, timeout: float | None = None) -> dict[str, Any]:
    """The JSON reply of ``<prefix>/<robot>/<what>``; TimeoutError when no service answers within the timeout.

    Every reply is collected, not only the first: more than one replying service on a robot's key (a second
    service, or a rogue peer answering in its place) is logged as a warning naming them.
    """
    timeout = settings.zenoh.query_timeout_s if timeout is None else timeout
    key = f"{settings.key_prefix}/{what}"
    session = open_session(settings.zenoh, "client")
    try:
        answers = collect_answers(session, key, timeout)
    finally:
        session.close()
    if not answers:
        raise TimeoutError(f"no reply on {key} within {timeout:g} s (is `objslam serve` running and reachable?)")
    return first_good(key, answers)


def collect_answers(session: zenoh.Session, key: str, timeout: float, grace: float = GRACE_S) -> list[Answer]:
    """The replies to ``key``: until ``timeout`` for the first one (the query is sent again while it ends empty,
    so the wait really is ``timeout``), then ``grace`` seconds more for others."""
    deadline = time.monotonic() + timeout
    answers: list[Answer] = []
    while not answers and (remaining := deadline - time.monotonic()) > 0:
        answers = _drain(_ask(session, key, remaining), deadline, grace)
        if not answers:
            time.sleep(max(0.0, min(RETRY_S, deadline - time.monotonic())))
    return answers


def _ask(session: zenoh.Session, key: str, timeout: float) -> queue.Queue[Answer | None]:
    """Send one query to every matching queryable; its answers arrive in the returned queue, then None."""
    inbox: queue.Queue[Answer | None] = queue.Queue()

    def on_reply(reply: zenoh.Reply) -> None:
        inbox.put(_answer(reply))

    session.get(
        key,
        zenoh.handlers.Callback(on_reply, lambda: inbox.put(None)),
        target=zenoh.QueryTarget.ALL,
        consolidation=zenoh.ConsolidationMode.NONE,  # replies on one key from two services are both kept
        timeout=timeout,
    )
    return inbox


def _drain(inbox: queue.Queue[Answer | None], deadline: float, grace: float) -> list[Answer]:
    """Answers from ``inbox`` until the query ends (None), the deadline, or ``grace`` after the first answer."""
    answers: list[Answer] = []
    until = deadline
    while (wait := until - time.monotonic()) > 0:
        try:
            item = inbox.get(timeout=wait)
        except queue.Empty:
            break
        if item is None:
            break
        answers.append(item)
        if len(answers) == 1:
            until = min(deadline, time.monotonic() + grace)
    return answers


def _answer(reply: zenoh.Reply) -> Answer:
    """A reply as plain data (taken inside zenoh's callback)."""
    replier = getattr(reply, "replier_id", None)
    sender = str(getattr(replier, "zid", replier)) if replier is not None else "unknown"
    if reply.ok is None:
        error = reply.err.payload.to_string() if reply.err is not None else "(no payload)"
        return Answer(None, error, sender)
    try:
        body = json.loads(reply.ok.payload.to_bytes())
    except (ValueError, UnicodeDecodeError):
        return Answer(None, "the reply is not JSON", sender)
    if not isinstance(body, dict):
        return Answer(None, "the reply is not a JSON object", sender)
    return Answer(body, "", str(body.get("service_id", sender)))


def first_good(key: str, answers: list[Answer]) -> dict[str, Any]:
    """The first reply that is a JSON object, after a warning when more than one reply or service answered."""
    services = list(dict.fromkeys(a.service_id for a in answers))
    if len(answers) > 1 or len(services) > 1:
        log.warning(
            "%d replies on %s from %d service(s) %s: another zenoh peer may be answering in the service's place; "
            "using the first good reply",
            len(answers),
            key,
            len(services),
            ", ".join(services),
        )
    for answer in answers:
        if answer.body is not None:
            return answer.body
    raise RuntimeError(f"{key}: service replied with an error: {answers[0].error}")


def _text(value: Any) -> Text:
    """A value as plain text: a reply's strings are data, never rich markup (``[/x]`` would raise)."""
    return Text(json.dumps(value) if isinstance(value, (dict, list)) else str(value))


def render_reply(console: Console, what: str, reply: dict[str, Any]) -> None:
    """A human-readable table of a reply; every value printed as plain text."""
    if what == "status":
        _render_status(console, reply)
    elif what == "trajectory":
        poses = reply.get("poses", [])
        console.print(Text(f"{len(poses)} poses ({reply.get('format')})"))
        for row in poses[-10:]:
            console.print(Text(" ".join(f"{v:.4f}" if isinstance(v, (int, float)) else str(v) for v in row)))
    else:
        items = reply.get(what, [])
        console.print(Text(f"{len(items)} {what}"))
        for item in items[:50]:
            console.print(Text(json.dumps(item)))


def _render_status(console: Console, reply: dict[str, Any]) -> None:
    table = Table(title=_text(f"objslam status: {reply.get('robot')}"), show_header=False)
    for key, value in reply.items():
        if key != "latency":
            table.add_row(_text(key), _text(value))
    console.print(table)
    lat = Table(title="stage latency (ms)")
    for col in ("stage", "n", "p50", "p95", "p99", "max"):
        lat.add_column(col)
    latency = reply.get("latency")
    for stage, s in (latency if isinstance(latency, dict) else {}).items():
        if isinstance(s, dict) and s.get("n"):
            lat.add_row(_text(stage), *(_text(s.get(k)) for k in ("n", "p50_ms", "p95_ms", "p99_ms", "max_ms")))
    console.print(lat)
