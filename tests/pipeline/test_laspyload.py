"""laspy loads without ``requests`` (`pipeline.laspyload`), which stays importable."""

import subprocess
import sys

_PROBE = """
import sys
import pipeline.reading, pipeline.formats.copc, pipeline.laswriting
print("requests:", "requests" in sys.modules, "laspy:", "laspy" in sys.modules)
import requests
print("later:", requests.__name__, "requests" in sys.modules)
"""


def test_laspy_loads_without_requests_which_stays_importable():
    p = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    assert p.stdout.split() == ["requests:", "False", "laspy:", "True", "later:", "requests", "True"]
