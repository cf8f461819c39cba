"""Progress of long work, one helper for every stage: tqdm's bar on a terminal, and the same status as one plain
line every `LINE_INTERVAL` seconds otherwise (a log file, CI, a pipe), where a bar's carriage returns would
flood the file.

    with progress(total=len(cells), desc="robustness_sweep", unit="run") as bar:
        for cell in cells:
            ...
            bar.update()

Both are tqdm objects (`update`, `set_postfix_str`, `total`, iteration over `progress(iterable)`); only where
and how often they write differs.
"""

from __future__ import annotations

import sys

from tqdm import tqdm

LINE_INTERVAL = 15.0  # seconds between progress lines when stderr is not a terminal
DELAY = 2.0           # seconds before anything is shown: quick work stays quiet
LINE_FORMAT = "{desc}: {n_fmt}/{total_fmt} {unit} [{elapsed} elapsed, {remaining} left{postfix}]"


class _Lines:
    """A file for tqdm that turns each status it draws (`\\r<status>`) into one line; blanks are dropped."""

    def __init__(self, file):
        self.file = file

    def write(self, s: str) -> None:
        s = s.replace("\r", "").strip()
        if s:
            self.file.write(s + "\n")

    def flush(self) -> None:
        self.file.flush()


class _Bar(tqdm):
    """tqdm that a Ctrl-C in the middle of its `__init__` leaves quiet: its `__del__` would read attributes never
    set (`'_LineBar' object has no attribute 'disable'` or `... 'last_print_t'`, a traceback after the one-line
    interruption), so it closes only a bar whose `__init__` ran to its end.

    No monitor thread (`monitor_interval = 0`): tqdm's first bar starts one, registering its `exit` with atexit
    *before* starting it, so a Ctrl-C between the two left a callback that joins a thread never started
    (`Exception ignored in atexit callback ... cannot join thread before it is started` after the one-line
    interruption; seen in CI). The monitor only lowers `miniters` of bars that draw too rarely; these bars draw on
    time (`mininterval`, `delay`)."""

    monitor_interval = 0

    def __init__(self, *args, **kwargs) -> None:  # noqa: D107 - tqdm's own keywords, passed through unchanged
        super().__init__(*args, **kwargs)
        self._initialised = True

    def __del__(self) -> None:
        if getattr(self, "_initialised", False):
            super().__del__()


class _LineBar(_Bar):
    """tqdm drawing one line per `mininterval`: a new postfix waits for the next line instead of drawing one."""

    def set_postfix_str(self, s: str = "", refresh: bool = False) -> None:
        super().set_postfix_str(s, refresh=False)


def is_terminal(file=None) -> bool:
    file = sys.stderr if file is None else file
    try:
        return bool(file.isatty())
    except (AttributeError, ValueError):  # a closed or odd stream
        return False


def progress(iterable=None, *, total: float | None = None, desc: str = "", unit: str = "it",
             enabled: bool = True, file=None, interval: float | None = None, unit_scale: bool = False) -> tqdm:
    """A progress bar on a terminal, periodic one-line progress otherwise (`interval` seconds, default
    `LINE_INTERVAL`); `enabled=False`: silent (tqdm's `disable`)."""
    file = sys.stderr if file is None else file
    if is_terminal(file):
        return _Bar(iterable, total=total, desc=desc, unit=unit, unit_scale=unit_scale, leave=False, file=file,
                    dynamic_ncols=True, delay=DELAY, disable=not enabled)
    every = LINE_INTERVAL if interval is None else interval
    return _LineBar(iterable, total=total, desc=desc, unit=unit, unit_scale=unit_scale, leave=False,
                    file=_Lines(file), bar_format=LINE_FORMAT, mininterval=every, maxinterval=max(every, 1.0),
                    miniters=1, delay=DELAY if interval is None else 0.0, disable=not enabled)
