"""Progress bars of the command line: :func:`drake_cert.progress.progress_bar` (the library's,
so that library code such as training writes the same whole lines to a log)."""

from drake_cert.progress import progress_bar

__all__ = ["progress_bar"]
