"""spatialseg: segment an event camera's stream by 3-D motion (EDPA + volume of warped events)."""

from spatialseg.events import EventStream
from spatialseg.recording import Camera, DepthMap, GroundTruth, Keyframe, Recording

__all__ = ["Camera", "DepthMap", "EventStream", "GroundTruth", "Keyframe", "Recording"]
__version__ = "0.1.0"
