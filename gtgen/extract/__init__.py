"""``gtgen extract``: a drive's bags -> a time-indexed drive store (``run_extract``)."""

from gtgen.extract.run import ExtractResult, run_extract

__all__ = ["ExtractResult", "run_extract"]
