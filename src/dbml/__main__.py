"""``python -m dbml``."""

from dbml.cli import run

run()
