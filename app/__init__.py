"""isolume's application layer: GL contexts, renderer, viewer and the command line.

Imports `volumes` and `baking` (public API only); nothing imports `app`.
"""

import time as _time

STARTED = _time.perf_counter()
"""`time.perf_counter` when the application was imported (the process's start, less
Python's own): what the viewer's script counts its waits from."""
