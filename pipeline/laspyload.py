"""laspy, loaded without ``requests``: modules import it as ``from pipeline.laspyload import laspy``.

laspy's COPC module imports ``requests`` (with urllib3, charset_normalizer and idna:
0.09-0.12 s of CPU, a fifth of a run's start-up before its first point) to read COPC
files over HTTP, which orchard never does. Hidden while laspy loads, ``requests`` is
missing to laspy alone (its HTTP reader would say so); whatever imports ``requests``
later gets it as usual.
"""

import sys

if "laspy" not in sys.modules and "requests" not in sys.modules:
    sys.modules["requests"] = None  # `import requests` raises ModuleNotFoundError, which laspy expects
    try:
        import laspy
    finally:
        del sys.modules["requests"]

import laspy  # noqa: E402 - loaded above, or before this module by someone else
