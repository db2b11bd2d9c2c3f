"""Recording benchmark tables in docs/benchmarks.md, one marked section per benchmark."""

from __future__ import annotations

import datetime as dt
import os
import platform
import re
from collections.abc import Sequence
from pathlib import Path

DEFAULT_FILE = Path("docs/benchmarks.md")


def machine() -> str:
    """A one-line description of the machine the figure was measured on."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    return f"{os.cpu_count()} cores ({cpu}), {mem:.0f} GiB, Python {platform.python_version()}"


def load_note(load: float) -> str:
    """A sentence for a table's notes when other work shared the machine while it was measured."""
    cores = os.cpu_count() or 1
    if load <= cores * 0.75:
        return ""
    return (
        f" Measured while other jobs ran on the machine (1-minute load average {load:.1f} on {cores} cores): "
        "times are longer and rates lower than on an idle machine."
    )


class StealMeter:
    """Share of CPU time the hypervisor gave to other guests (``steal`` in /proc/stat) since construction.

    On a shared virtual machine this, more than the load average, explains runs that are slower than the
    code: a 2-core guest with 20 % stolen has 1.6 cores."""

    def __init__(self) -> None:
        self._start = self._read()

    @staticmethod
    def _read() -> tuple[int, int] | None:
        try:
            fields = Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]
        except OSError:  # not Linux
            return None
        values = [int(v) for v in fields]
        return sum(values[:8]), values[7] if len(values) > 7 else 0

    def percent(self) -> float:
        end = self._read()
        if self._start is None or end is None or end[0] <= self._start[0]:
            return float("nan")
        return 100.0 * (end[1] - self._start[1]) / (end[0] - self._start[0])


def show_table(console, title: str, header: list[str], rows: Sequence[Sequence[object]]) -> None:
    """Print a benchmark table to the terminal (rich)."""
    from rich.table import Table

    table = Table(title=title)
    for h in header:
        table.add_column(h)
    for row in rows:
        table.add_row(*map(str, row))
    console.print(table)


def markdown_table(header: list[str], rows: Sequence[Sequence[object]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def record(name: str, title: str, command: str, table: str, notes: str = "", path: Path | None = None) -> Path:
    """Replace (or append) the ``name`` section of the benchmarks file with a fresh table."""
    path = path or DEFAULT_FILE
    body = (
        f"<!-- bench:{name} -->\n## {title}\n\n"
        f"Command: `{command}`  \nMachine: {machine()}  \nDate: {dt.date.today().isoformat()}\n\n"
        f"{table}\n" + (f"\n{notes}\n" if notes else "") + f"<!-- /bench:{name} -->"
    )
    text = path.read_text() if path.is_file() else "# objslam benchmarks\n\nMeasured tables, newest run of each.\n"
    pattern = re.compile(rf"<!-- bench:{re.escape(name)} -->.*?<!-- /bench:{re.escape(name)} -->", re.S)
    text = pattern.sub(lambda _: body, text) if pattern.search(text) else text.rstrip() + "\n\n" + body + "\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path
