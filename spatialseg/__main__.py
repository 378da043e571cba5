"""``python -m spatialseg``: the Hydra entry point (see :mod:`spatialseg.cli`)."""

import sys

from spatialseg.tracking_process import start_early


def main() -> None:
    """Start the tracking worker, then import and run the app: MLflow's imports in the
    worker overlap the app's own (:mod:`spatialseg.tracking_process`)."""
    start_early(sys.argv[1:])
    from spatialseg.cli import main as app

    app()


if __name__ == "__main__":
    main()
