"""``python -m spatialseg.simulate``: the Hydra app (see :mod:`spatialseg.simulate.app`)."""

from spatialseg.simulate.app import main

if __name__ == "__main__":
    main()
