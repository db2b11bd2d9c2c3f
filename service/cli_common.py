"""What the ``objslam`` command line's parts share: the console, the user error, camera flags."""

from __future__ import annotations

from rich.console import Console

console = Console()


class UserError(Exception):
    """An error to print as one line before exiting non-zero."""


def camera_overrides(**values: float | None) -> dict[str, float]:
    return {k: v for k, v in values.items() if v is not None}
