"""The gtgen error hierarchy.

Every error a user can cause is a :class:`GtgenError`. Subclasses also inherit the
builtin they resemble, so callers may catch either (``except FileNotFoundError``).
"""


class GtgenError(Exception):
    """Base class of every error gtgen raises on purpose."""


class ConfigError(GtgenError, ValueError):
    """A configuration value or command-line argument is invalid."""


class InputNotFoundError(GtgenError, FileNotFoundError):
    """An input file or folder does not exist."""


class BagError(GtgenError, ValueError):
    """A bag cannot be opened or decoded."""


class TopicError(GtgenError, KeyError):
    """A role's topic is missing from the bags or has the wrong type."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0]) if self.args else ""


class DecodeError(GtgenError, ValueError):
    """A message has contents gtgen cannot interpret (layers, layout, frames)."""


class StoreError(GtgenError, ValueError):
    """A drive store or dataset is missing, incomplete, or of another version."""


class PoseError(GtgenError, ValueError):
    """A pose was asked for outside the time span odometry covers."""


class DemError(GtgenError, ValueError):
    """DEM tiles are missing, unreadable, or do not cover the drive."""


class AlignmentError(GtgenError, ValueError):
    """The drive cannot be placed in the DEM's coordinate system."""


class TrainError(GtgenError, ValueError):
    """Training or evaluation cannot run on the given data or checkpoint."""


class RankError(TrainError):
    """Under torchrun, the error of rank 0 as another process received it: rank 0 reports
    it, the others stop without repeating it."""


class LockedError(GtgenError, BlockingIOError):
    """Another gtgen command is writing (or reading) the same output."""


class OutputExistsError(GtgenError, FileExistsError):
    """An output path holds something gtgen did not write (pass --overwrite to replace it)."""


class WorkerDiedError(GtgenError, RuntimeError):
    """A worker process of a pool ended abruptly (killed by the system, say for memory)."""
