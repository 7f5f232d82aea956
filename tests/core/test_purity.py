import subprocess
import sys


def test_core_imports_no_middleware_runtime_or_threads() -> None:
    code = (
        "import sys, dbml.core, dbml.scenarios; "
        "bad = [m for m in sys.modules "
        "if m.split('.')[0] in {'zenoh', 'rospy', 'rosgraph', 'rich'} "
        "or m.startswith(('dbml.runtime', 'dbml.transports', 'dbml.testbed', 'dbml.cli'))]; "
        "print(','.join(sorted(bad)))"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True
    )
    assert result.stdout.strip() == ""
