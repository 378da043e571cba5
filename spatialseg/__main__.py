"""``python -m spatialseg``: the Hydra entry point (see :mod:`spatialseg.cli`)."""

from spatialseg.cli import main

if __name__ == "__main__":
    main()
