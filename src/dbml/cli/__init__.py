"""The ``dbml`` command line: parser, handlers, command bodies and rendering."""

from dbml.cli.main import main

__all__ = ["main"]
