"""Settings are defined once and every one reaches the component that uses it.

Each section of ``objslam config --dump`` is a pydantic model defined beside its component; the component
holds that very section object (no copy into a twin dataclass that could drop a field), and every field is
read by name somewhere in the code.
"""

from __future__ import annotations

import re
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from pydantic import BaseModel

from service.config import Settings, dump_defaults, load_settings
from slam.build import build_core
from tests.conftest import make_frame

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("service", "slam", "loops", "graph", "perception", "rl", "sources", "evaluation")
SLAM_SECTIONS = ("keyframes", "odometry", "loops", "detector", "objects", "graph")


def _reachable_models(root: Any, limit: int = 200_000) -> set[int]:
    """ids of every pydantic model reachable from ``root`` through attributes and containers, except through
    the whole ``Settings`` (a component must hold its own section, not look it up in the aggregate)."""
    seen: set[int] = set()
    models: set[int] = set()
    todo: deque[Any] = deque([root])
    while todo and len(seen) < limit:
        obj = todo.popleft()
        if (
            id(obj) in seen
            or obj is None
            or isinstance(obj, (str, bytes, int, float, bool, np.ndarray, type, Settings))
        ):
            continue
        seen.add(id(obj))
        if isinstance(obj, BaseModel):
            models.add(id(obj))
        if isinstance(obj, dict):
            todo.extend(obj.values())
        elif isinstance(obj, (list, tuple, set, frozenset, deque)):
            todo.extend(obj)
        elif hasattr(obj, "__dict__"):
            todo.extend(vars(obj).values())
        if hasattr(obj, "__closure__") and obj.__closure__:  # factories built from settings
            todo.extend(cell.cell_contents for cell in obj.__closure__)
    return models


def test_the_slam_core_holds_the_very_section_objects_of_the_settings():
    settings = load_settings(None, {"detector": {"enabled": False}})
    core = build_core(settings)
    core.step(make_frame(t=1.0))  # the tracking components are built at the first frame
    reached = _reachable_models(core)
    missing = [name for name in SLAM_SECTIONS if id(getattr(settings, name)) not in reached]
    assert not missing, f"sections no component holds: {missing}"


def _production_source() -> str:
    return "\n".join(p.read_text() for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py"))


def test_every_setting_of_the_dump_is_read_by_name_in_the_code():
    dumped = yaml.safe_load(dump_defaults())
    source = _production_source()
    unread = []
    for section, fields in dumped.items():
        if not isinstance(fields, dict):
            assert f".{section}" in source, section
            continue
        model = Settings.model_fields[section].annotation
        assert isinstance(model, type) and issubclass(model, BaseModel), section
        assert set(fields) == set(model.model_fields), f"{section}: the dump and the section disagree"
        for name in fields:
            if not re.search(rf"\.{name}\b", source):
                unread.append(f"{section}.{name}")
    assert not unread, f"settings nothing reads: {unread}"
