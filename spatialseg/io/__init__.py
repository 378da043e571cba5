"""Reading and writing recordings and event files on disk (formats: ``docs/formats.md``).

* :func:`read_recording` / :func:`write_recording`: a recording directory (RPG Event Camera
  Dataset layout plus depth maps); writing is atomic (temporary sibling, then rename).
* :func:`read_events` / :func:`write_events`: a bare ``.txt``, ``.h5``/``.hdf5`` (DSEC
  layout) or ``.npz`` events file; writing is atomic (temporary file, then rename).
* :func:`read_any`: any supported type, picked by what the path is: a recording directory,
  ``.txt``, ``.h5``/``.hdf5``, ``.npz``, ``.aedat4`` (iniVation DV, with APS frames as
  keyframes), ``.raw`` (Prophesee EVT 2.0/3.0) or ``.dat`` (Prophesee DAT).
* :func:`iter_event_chunks`: the events of any of them, a fixed number at a time, in
  bounded memory. :func:`write_prophesee` writes ``.raw``/``.dat`` (tests, conversion).

Malformed input raises ``ValueError`` (``FileNotFoundError`` for a missing file) whose
one-line message names the file, the line (or event index) and the fix; so does a damaged
file, whatever its decoder raised (``spatialseg.io._decode``), a Rust panic included.
"""

from spatialseg.io._directory import read_recording, write_recording
from spatialseg.io._events import read_events, write_events
from spatialseg.io._prophesee import write_prophesee
from spatialseg.io._readany import SUPPORTED, nominal_camera, read_any
from spatialseg.io._stream import iter_event_chunks

__all__ = [
    "SUPPORTED",
    "iter_event_chunks",
    "nominal_camera",
    "read_any",
    "read_events",
    "read_recording",
    "write_events",
    "write_prophesee",
    "write_recording",
]
