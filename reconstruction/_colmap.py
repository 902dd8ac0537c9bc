"""pycolmap, imported first by the package, without the SIGTERM handler its logging library installs on import.

glog's failure handler answers SIGTERM (`timeout`, `docker stop`, a cancelled CI job) with a 35-line stack dump and
kills the process on the spot, so the output stages never remove their half-written folders. The handler that was
in place before the import (the command line's own, which unwinds the stages as Ctrl-C does, or the default) is
put back; glog keeps its handlers for real crashes (SIGSEGV, SIGABRT, ...).
"""

from __future__ import annotations

import signal
import threading

# OpenCV before pycolmap (the package's __init__ says why and warns when a user loaded pycolmap first).
import cv2  # noqa: F401

_in_main_thread = threading.current_thread() is threading.main_thread()  # signal.signal works only there
_before = signal.getsignal(signal.SIGTERM) if _in_main_thread else None

import pycolmap  # noqa: E402  (after reading the handler it replaces)

if _before is not None:
    signal.signal(signal.SIGTERM, _before)

__all__ = ["pycolmap"]
