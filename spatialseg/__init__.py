"""spatialseg: segment an event camera's stream by 3-D motion (EDPA + volume of warped events).

The Python API (:mod:`spatialseg.api`): :func:`simulate` or :func:`read` a Recording,
:func:`segment` it (or :class:`MotionSegmenter`), :func:`write` it; :class:`Settings` holds
every setting of the method with its default (:mod:`spatialseg.settings`).
"""

import os
from importlib import import_module
from typing import TYPE_CHECKING, Any

# Decision: the kernels' OpenMP threads sleep while they wait for work, unless the
# environment chooses: spinning, they starve any other process on the cores (a second job,
# a browser), and a 15,000-event window took 0.23 s alone but 1.7 s beside one busy core,
# 0.28 s asleep (docs/performance.md, session 57). Set before numba's OpenMP starts.
if "OMP_WAIT_POLICY" not in os.environ and "GOMP_SPINCOUNT" not in os.environ:
    os.environ["OMP_WAIT_POLICY"] = "PASSIVE"

from spatialseg.events import EventStream
from spatialseg.recording import Camera, DepthMap, GroundTruth, Keyframe, Recording
from spatialseg.settings import Settings, settings_from

if TYPE_CHECKING:
    from spatialseg.api import Segmentation, read, segment, simulate, write
    from spatialseg.estimator import MotionSegmenter

__all__ = [
    "Camera",
    "DepthMap",
    "EventStream",
    "GroundTruth",
    "Keyframe",
    "MotionSegmenter",
    "Recording",
    "Segmentation",
    "Settings",
    "read",
    "segment",
    "settings_from",
    "simulate",
    "write",
]
__version__ = "0.1.0"

#: The API's names and their modules, imported on first use (:func:`__getattr__`): the API
#: loads the pipeline, the estimator scikit-learn.
_API = {
    "MotionSegmenter": "spatialseg.estimator",
    **dict.fromkeys(("Segmentation", "read", "segment", "simulate", "write"), "spatialseg.api"),
}

# The simulator subpackage shares its name with the API's simulate(). Imported now, it
# binds the package attribute ``simulate`` here and never again, so the name is freed for
# the function whichever of the two a user imports first.
import_module("spatialseg.simulate")
del globals()["simulate"]


def __getattr__(name: str) -> Any:
    """The API's names (:mod:`spatialseg.api`, :mod:`spatialseg.estimator`), imported on
    first use (PEP 562)."""
    if name not in _API:
        raise AttributeError(f"module 'spatialseg' has no attribute {name!r}")
    value = getattr(import_module(_API[name]), name)
    globals()[name] = value
    return value
