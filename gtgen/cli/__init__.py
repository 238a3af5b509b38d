"""The ``gtgen`` command line (see ``gtgen.cli.app``); importing it registers every command."""

# the commands register themselves on the app in this order, which is the order of
# ``gtgen --help``: the data flow
from gtgen.cli import stages  # noqa: F401, I001
from gtgen.cli import views  # noqa: F401
from gtgen.cli import learn  # noqa: F401
from gtgen.cli import export  # noqa: F401
from gtgen.cli.app import app, main

__all__ = ["app", "main"]
