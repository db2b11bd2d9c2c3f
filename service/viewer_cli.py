"""The viewer's command-line flags of ``run`` and ``serve`` (settings section ``viewer``), and what they ask for.

Light on purpose: ``rerun`` (``service.viewer_feed``) is imported only when a viewer or a recording is wanted."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

from service.config import Settings, ViewerSettings

RerunOpt = Annotated[
    bool, typer.Option("--rerun", help="stream to a native Rerun viewer (viewer.connect), started if none runs")
]
RerunWebOpt = Annotated[
    int | None,
    typer.Option("--rerun-web", min=1, max=65535, help="serve the Rerun web viewer on 127.0.0.1:PORT"),
]
RrdOpt = Annotated[Path | None, typer.Option("--rrd", help="record the map into this .rrd file (rerun FILE)")]
NoRrdOpt = Annotated[bool, typer.Option("--no-rrd", help="run: no OUT/map.rrd recording")]


def viewer_overrides(rerun: bool, web_port: int | None, rrd: Path | None, no_rrd: bool = False) -> dict[str, Any]:
    """The ``viewer`` settings the flags set (the others stay as configured)."""
    over: dict[str, Any] = {"native": True} if rerun else {}
    if web_port is not None:
        over["web_port"] = web_port
    if rrd is not None:
        over["rrd"] = rrd
    if no_rrd:
        over["enabled"] = False
    return {"viewer": over} if over else {}


def run_rrd(settings: Settings, out: Path) -> Path | None:
    """The recording of ``run``: ``viewer.rrd``, else ``OUT/map.rrd`` unless ``viewer.enabled`` is off."""
    if settings.viewer.rrd is not None:
        return Path(settings.viewer.rrd)
    return out / "map.rrd" if settings.viewer.enabled else None


def viewer_wanted(viewer: ViewerSettings, rrd: Path | None) -> bool:
    """A recording, the web viewer or a native viewer is asked for."""
    return rrd is not None or viewer.web_port is not None or viewer.native
