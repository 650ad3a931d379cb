"""A stop asked for with SIGINT or SIGTERM, honoured between generations: the loops of
`python -m pgps_jax.train` and of the paper experiments' cells write a checkpoint of the state
they stopped at, so that the same command continues from there. Outside the loops (while the
programs compile, say), `sigterm_as_ctrl_c` makes SIGTERM stop the command as Ctrl-C does."""

import contextlib
import signal
import sys
from typing import Optional

from tqdm import tqdm


class StopRequest:
    """Turns the first SIGINT/SIGTERM into a request to checkpoint and stop after the current
    generation; a second Ctrl-C aborts at once (KeyboardInterrupt)."""

    def __init__(self):
        self.requested: Optional[str] = None
        self._previous = {}

    def __enter__(self):
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum, frame):
        if self.requested is not None and signum == signal.SIGINT:
            raise KeyboardInterrupt
        self.requested = signal.Signals(signum).name
        tqdm.write(f"\n{self.requested}: stopping after this generation and writing a "
                   f"checkpoint (Ctrl-C again to abort without one)", file=sys.stderr)

    def __exit__(self, *exc):
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        return False


@contextlib.contextmanager
def sigterm_as_ctrl_c():
    """While inside, SIGTERM raises KeyboardInterrupt as Ctrl-C does (Python's default for it
    ends the process on the spot, skipping every `finally`); a `StopRequest` inside takes both
    signals over for its loop."""
    previous = signal.signal(signal.SIGTERM, _raise_keyboard_interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _raise_keyboard_interrupt(signum, frame):
    raise KeyboardInterrupt
