"""The report's map drawn by a forked process (`service.reports.mapprocess`): the same
bytes as drawn here, and drawn here whenever the child cannot.

The cases run in fresh interpreters: a pytest process may hold threads (the shared
cluster), where `MapProcess.start` rightly declines to fork. Two interpreters in all,
matplotlib being most of their time.
"""

import subprocess
import sys

_PROBE = """
import os, signal, sys, threading
import numpy as np
from service.reports.mapprocess import MapProcess

rng = np.random.default_rng(3)
xy = rng.uniform(0, 20, (5000, 2))
args = (xy, rng.integers(-1, 6, 5000), np.array([[4.0, 5.0], [12.0, 9.0]]), np.array([1, 2]))

{body}
"""


def _run(body: str) -> list[str]:
    p = subprocess.run([sys.executable, "-c", _PROBE.format(body=body)], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    return p.stdout.split()


def test_the_childs_map_is_the_map_drawn_here_and_a_child_gone_leaves_it_to_this_process():
    out = _run("""
maps = MapProcess.start()
assert maps.pid is not None
png = maps.draw(*args, title="Orchard report — $x$.laz")()
print("matplotlib-here:", "matplotlib" in sys.modules, "reaped:", maps.pid is None)

gone = MapProcess.start()
os.kill(gone.pid, signal.SIGKILL)  # not reaped: its pid stays its own until close() waits for it
again = gone.draw(*args, title="Orchard report — $x$.laz")()

unused = MapProcess.start()
pid = unused.pid
unused.close()  # a run that ended without a map
try:
    os.waitpid(pid, os.WNOHANG)
    print("unused: still a child")
except ChildProcessError:
    print("unused: reaped")

from service.reports.mapimage import render_map_png
here = render_map_png(*args, title="Orchard report — $x$.laz")
print("same:", png == here, again == here, png[:4] == b"\\x89PNG")
""")
    assert out == ["matplotlib-here:", "False", "reaped:", "True", "unused:", "reaped", "same:", "True", "True", "True"]


def test_a_map_that_cannot_be_drawn_fails_here_as_before_and_no_fork_beside_another_thread():
    out = _run("""
maps = MapProcess.start()
result = maps.draw(xy, np.zeros(len(xy)), np.zeros((0, 2)), np.zeros(0), title="t")  # float ids: not an index
try:
    result()
except IndexError:
    print("IndexError")
print("reaped:", maps.pid is None)

stop = threading.Event()
t = threading.Thread(target=stop.wait)
t.start()
maps = MapProcess.start()
print("forked:", maps.pid is not None)
print("png:", maps.draw(*args, title="t")()[:4] == b"\\x89PNG")
stop.set()
t.join()
""")
    assert out == ["IndexError", "reaped:", "True", "forked:", "False", "png:", "True"]
