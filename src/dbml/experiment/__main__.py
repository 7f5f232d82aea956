"""``python -m dbml.experiment KIND ...``: a child process of a demo or testbed run."""

from dbml.experiment.entry import main
from dbml.harness.processes import exit_process

exit_process(main)
