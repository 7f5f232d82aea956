"""The ``dbml`` command line: parser, handlers, command bodies and rendering."""

from dbml.cli.main import main
from dbml.harness.processes import exit_process

__all__ = ["main", "run"]


def run() -> None:
    """The ``dbml`` command: ``main``, then the process ends with its code (``exit_process``)."""
    exit_process(main)
