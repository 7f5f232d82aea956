"""``python -m dbml.experiment KIND ...``: a child process of a demo or testbed run."""

import sys

from dbml.experiment.entry import main

sys.exit(main())
