"""Progress bars of the CLI: tqdm on stderr, counted in the user's units (PSFs, steps, files), with an ETA.

Every command that can run longer than ~10 s shows one; ``raywave --quiet COMMAND`` (or ``COMMAND --quiet``)
turns them all off. A bar appears after :data:`DELAY_S` seconds, so quick commands print nothing extra. A unit of
work that takes long on its own (one PSF) is wrapped in :func:`ticking`, which redraws the bar every second so that
its elapsed time keeps moving: no command is silent for more than a few seconds.
"""

from __future__ import annotations

import contextlib
import sys
import threading
import time

from tqdm.auto import tqdm

__all__ = ["DELAY_S", "bar", "is_quiet", "ticking"]

#: seconds before a bar is drawn (tqdm's ``delay``): commands that finish sooner stay as they were
DELAY_S = 2.0


def is_quiet(args) -> bool:
    """Whether the command's progress bars are off (``--quiet`` before or after the command name)."""
    return bool(getattr(args, "quiet", False) or getattr(args, "quiet_global", False))


def bar(args, total: int | None, unit: str, desc: str) -> tqdm:
    """A progress bar of ``total`` ``unit`` s (e.g. ``"PSF"``) on stderr, off with ``--quiet``."""
    return tqdm(total=total, unit=unit, desc=desc, disable=is_quiet(args), file=sys.stderr, delay=DELAY_S,
                dynamic_ncols=True, leave=False)


@contextlib.contextmanager
def ticking(pbar: tqdm, every_s: float = 1.0):
    """Redraw ``pbar`` every ``every_s`` seconds while the block runs (its elapsed time and ETA stay current during
    one long unit of work); a daemon thread, stopped when the block ends."""
    if pbar.disable:
        yield pbar
        return
    stop = threading.Event()

    def run():
        while not stop.wait(every_s):
            if time.time() < pbar.start_t + pbar.delay:  # tqdm's delay: not drawn yet
                continue
            try:
                pbar.refresh()
            except Exception:  # noqa: BLE001 - a closed bar or stream: stop redrawing
                return
            # tqdm's close() clears only a bar it knows was drawn (last_print_t past its delay), and refresh() does
            # not set it: a bar drawn here alone stayed on the line, and an error printed after it joined it. The
            # earliest such time, so that update()'s own redraw (mininterval after the last print) is not held back
            pbar.last_print_t = max(pbar.last_print_t, pbar.start_t + pbar.delay)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    try:
        yield pbar
    finally:
        stop.set()
        t.join()
