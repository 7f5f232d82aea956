"""``python -m dbml``."""

import sys

from dbml.cli import main

sys.exit(main())
