"""Progress bars on stderr, for the command line and the library's long loops (training).

On a terminal a live bar; in a log file (a long run in the background, a CI log) one ASCII line
a minute plus the first and the last, so that the log shows progress without filling up with
carriage-return redraws.
"""

import sys


class _LineWriter:
    """A stream for tqdm in a log: each redraw becomes one whole line (tqdm redraws with a
    carriage return and ends the line only when it closes, so a log read line by line, or a
    CI log, would show nothing for the whole run)."""

    def __init__(self, stream):
        self.stream = stream

    def write(self, text: str) -> None:
        text = text.replace("\r", "").rstrip("\n")
        if text.strip():
            self.stream.write(text + "\n")

    def flush(self) -> None:
        self.stream.flush()


def progress_bar(iterable=None, **options):
    """A ``tqdm`` bar on stderr with the refresh rate set by whether stderr is a terminal."""
    from tqdm import tqdm

    tty = sys.stderr.isatty()
    options.setdefault("file", sys.stderr if tty else _LineWriter(sys.stderr))
    options.setdefault("mininterval", 0.1 if tty else 60.0)
    options.setdefault("ascii", not tty)
    return tqdm(iterable, **options)
