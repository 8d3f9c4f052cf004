import sys

import pytest
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


# zenoh-python runs each Python callback on a non-daemon thread that ends only when zenoh drops
# the callback; one that zenoh keeps (e.g. a liveliness subscriber's history query still
# pending when its session closed) makes the interpreter wait for it at exit forever, after the
# summary was printed.  The product's zenoh processes exit hard for the same reason
# (bridge/cli/main.py HARD_EXIT); the test run does too, with pytest's exit status, but only then.
_EXIT_STATUS = [None]


def pytest_sessionfinish(session, exitstatus):
    _EXIT_STATUS[0] = int(exitstatus)


@pytest.hookimpl(trylast=True)
def pytest_unconfigure(config):
    import os
    import threading
    stuck = [t.name for t in threading.enumerate()
             if t is not threading.main_thread() and not t.daemon and t.is_alive()]
    if stuck and _EXIT_STATUS[0] is not None:
        sys.stdout.flush()
        sys.stderr.write(f"conftest: {len(stuck)} zenoh callback thread(s) still alive at exit "
                         f"({', '.join(stuck[:3])}); exiting without waiting for them\n")
        sys.stderr.flush()
        os._exit(_EXIT_STATUS[0])
