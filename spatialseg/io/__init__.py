"""Reading and writing recordings and event files on disk (formats: ``docs/formats.md``).

* :func:`read_recording` / :func:`write_recording`: a recording directory (RPG Event Camera
  Dataset layout plus depth maps); writing is atomic (temporary sibling, then rename).
* :func:`read_events` / :func:`write_events`: a bare ``.txt``, ``.h5``/``.hdf5`` (DSEC
  layout) or ``.npz`` events file; writing is atomic (temporary file, then rename).
* :func:`read_any`: a recording directory or a file of any registered format, by suffix:
  ``.txt``, ``.h5``/``.hdf5``, ``.npz``, ``.aedat4`` (iniVation DV, with APS frames as
  keyframes), ``.raw`` (Prophesee EVT 2.0/3.0) or ``.dat`` (Prophesee DAT).
* :func:`iter_event_chunks`: the events of any of them, a fixed number at a time, in
  bounded memory. :func:`write_prophesee` writes ``.raw``/``.dat`` (tests, conversion).
* :func:`register_format`: a new format, one decoder read whole and streamed (:class:`Block`,
  :func:`event_formats`); :data:`SUPPORTED` lists what ``read_any`` reads.

Malformed input raises ``ValueError`` (``FileNotFoundError`` for a missing file) whose
one-line message names the file, the line (or event index) and the fix; so does a damaged
file, whatever its decoder raised (``spatialseg.io._decode``), a Rust panic included.
"""

from spatialseg.io._decode import Block
from spatialseg.io._directory import read_recording, write_recording
from spatialseg.io._events import write_events
from spatialseg.io._formats import EventFormat, event_formats, register_format, supported
from spatialseg.io._prophesee import write_prophesee
from spatialseg.io._readany import nominal_camera, read_any, read_events
from spatialseg.io._stream import iter_event_chunks

__all__ = [
    "SUPPORTED",
    "Block",
    "EventFormat",
    "event_formats",
    "iter_event_chunks",
    "nominal_camera",
    "read_any",
    "read_events",
    "read_recording",
    "register_format",
    "write_events",
    "write_prophesee",
    "write_recording",
]


def __getattr__(name: str) -> str:
    """``SUPPORTED``: what :func:`read_any` reads, for messages and docs; computed on access, so
    it lists formats registered since import."""
    if name == "SUPPORTED":
        return supported()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
