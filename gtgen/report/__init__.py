"""``gtgen report``: a dataset card, QA figures, and on a synthetic drive the error against its truth."""

from gtgen.report.run import Report, build_report

__all__ = ["Report", "build_report"]
