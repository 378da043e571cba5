"""An ESIM-style event simulator with ground truth, for the paper's scenes (``conf/scene``).

A scene is a pinhole camera (static or translating at a constant ego-velocity), a static
scene of textured planes and props (boxes or patches at rest), and moving textured boxes
or patches with constant 3-D velocity. The output depth maps can be corrupted by a
configured depth error (:mod:`spatialseg.simulate.depth_error`). The scene is ray-cast
with a z-buffer at an adaptive rate (no point moves more than ``render.max_pixel_step``
pixels between renders), and a pixel emits an event each time its log intensity crosses
its reference by its contrast threshold (see :mod:`spatialseg.simulate.sensor`). Entry
point: :func:`simulate_scene`; command line: ``python -m spatialseg.simulate
+scene=interior out=DIR``.
"""

from importlib import import_module
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from spatialseg.simulate.scene import Scene, parse_scene
    from spatialseg.simulate.simulator import simulate_scene

__all__ = ["Scene", "parse_scene", "simulate_scene"]

#: Where each name lives. Imported on first use (PEP 562): ``import spatialseg`` imports
#: this package, and a run on a recording never needs the renderer (0.3 s of imports).
_HOMES = {
    "Scene": "spatialseg.simulate.scene",
    "parse_scene": "spatialseg.simulate.scene",
    "simulate_scene": "spatialseg.simulate.simulator",
}


def __getattr__(name: str) -> Any:
    """The simulator's names, imported on first use."""
    if name not in _HOMES:
        raise AttributeError(f"module 'spatialseg.simulate' has no attribute {name!r}")
    value = getattr(import_module(_HOMES[name]), name)
    globals()[name] = value
    return value
