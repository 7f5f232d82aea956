"""The ``dbml`` command line: parser, handlers and rendering."""

from dbml.cli.main import main

__all__ = ["main"]
