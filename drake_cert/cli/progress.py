"""Progress bars of the command line, on stderr.

On a terminal a live bar; in a log file (a long run in the background, a CI log) one ASCII line
a minute plus the first and the last, so that the log shows progress without filling up with
carriage-return redraws.
"""

import sys


def progress_bar(iterable=None, **options):
    """A ``tqdm`` bar on stderr with the refresh rate set by whether stderr is a terminal."""
    from tqdm import tqdm

    tty = sys.stderr.isatty()
    options.setdefault("file", sys.stderr)
    options.setdefault("mininterval", 0.1 if tty else 60.0)
    options.setdefault("ascii", not tty)
    return tqdm(iterable, **options)
