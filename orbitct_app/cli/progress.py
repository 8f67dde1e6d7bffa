"""Terminal progress bars fed by :class:`orbitct.progress.ProgressEvent`."""

from __future__ import annotations

import sys
from types import TracebackType

from tqdm import tqdm

from orbitct.progress import ProgressEvent


class ProgressBar:
    """A tqdm bar per stage; shown only on a terminal (and after the first second)."""

    def __init__(self, *, enabled: bool | None = None) -> None:
        self.enabled = sys.stderr.isatty() if enabled is None else enabled
        self._bars: dict[str, tqdm] = {}

    def __call__(self, event: ProgressEvent) -> None:
        if event.stage.endswith("-warning"):  # warnings are lines, shown on any stderr
            self.note(f"warning: {event.message}")
            return
        if event.stage == "duration":  # how long the work is expected to take: a line, before it starts
            self.note(event.message)
            return
        if not self.enabled:
            return
        try:
            self._show(event)
        except OSError:  # the terminal went away (SIGHUP): the work goes on without a bar
            self.enabled = False

    def _show(self, event: ProgressEvent) -> None:
        bar = self._bars.get(event.stage)
        if bar is None:
            bar = tqdm(total=event.total, desc=event.stage, unit="step", delay=1.0, leave=True, file=sys.stderr)
            self._bars[event.stage] = bar
        bar.total = event.total
        bar.n = event.done
        post = {k: (f"{v:.4g}" if isinstance(v, float) else v) for k, v in event.metrics.items()}
        if event.message:
            post["info"] = event.message
        bar.set_postfix(post, refresh=False)
        bar.refresh()

    def note(self, text: str) -> None:
        """A line above the bars (on stderr, terminal or not)."""
        try:
            if self.enabled:
                tqdm.write(text, file=sys.stderr)
            else:
                print(text, file=sys.stderr, flush=True)
        except OSError:
            self.enabled = False

    def close(self) -> None:
        """Close every bar."""
        for bar in self._bars.values():
            bar.close()
        self._bars.clear()

    def __enter__(self) -> ProgressBar:
        return self

    def __exit__(self, t: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None) -> None:
        self.close()
