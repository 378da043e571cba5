"""Reading and writing recordings and event files on disk (formats: ``docs/formats.md``).

* :func:`read_recording` / :func:`write_recording`: a recording directory (RPG Event Camera
  Dataset layout plus depth maps); writing is atomic (temporary sibling, then rename).
* :func:`read_events` / :func:`write_events`: a bare ``.txt``, ``.h5``/``.hdf5`` (DSEC
  layout) or ``.npz`` events file; writing is atomic (temporary file, then rename).

Malformed input raises ``ValueError`` (``FileNotFoundError`` for a missing file) whose
one-line message names the file, the line (or event index) and the fix.
"""

from spatialseg.io._directory import read_recording, write_recording
from spatialseg.io._events import read_events, write_events

__all__ = ["read_events", "read_recording", "write_events", "write_recording"]
