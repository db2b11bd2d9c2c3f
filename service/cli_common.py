"""What the ``objslam`` command line's parts share: the console, the user error, camera flags."""

from __future__ import annotations

import math

from rich.console import Console

console = Console()


class UserError(Exception):
    """An error to print as one line before exiting non-zero."""


def camera_overrides(**values: float | None) -> dict[str, float]:
    return {k: v for k, v in values.items() if v is not None}


def positive_finite(flag: str, value: float | None) -> None:
    """UserError unless ``value`` (when given) is a positive finite number: ``nan`` passes every comparison
    check and ``inf`` would make a rate of zero seconds per frame or an endless wait."""
    if value is not None and not (math.isfinite(value) and value > 0):
        raise UserError(f"{flag} must be a positive finite number (got {value:g})")
