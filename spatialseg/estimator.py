"""The scikit-learn form of :func:`spatialseg.segment`, in a module of its own: scikit-learn
takes about a second to import, which the Python API and the command line do not pay."""

from __future__ import annotations

from typing import Any

import numpy as np
from sklearn.base import BaseEstimator

from spatialseg.api import Segmentation, segment
from spatialseg.recording import Recording

__all__ = ["MotionSegmenter"]


class MotionSegmenter(BaseEstimator):
    """:func:`segment` as a scikit-learn style estimator: the same parameters;
    :meth:`fit` stores ``segmentation_`` and ``labels_`` and returns the Segmentation."""

    def __init__(
        self,
        n_clusters: int | str = 2,
        *,
        seed: int = 0,
        optimizer: Any = "ssa_ga",
        **settings: Any,
    ) -> None:
        self.n_clusters = n_clusters
        self.seed = seed
        self.optimizer = optimizer
        self.settings = settings

    def get_params(self, deep: bool = True) -> dict[str, Any]:
        """The parameters, ``settings`` flat among them (as :func:`segment` takes them)."""
        own = {"n_clusters": self.n_clusters, "seed": self.seed, "optimizer": self.optimizer}
        return {**own, **self.settings}

    def set_params(self, **params: Any) -> MotionSegmenter:
        """Change parameters; a name that is none of the arguments is a setting."""
        for key, value in params.items():
            if key in ("n_clusters", "seed", "optimizer"):
                setattr(self, key, value)
            else:
                self.settings = {**self.settings, key: value}
        return self

    def fit(self, recording: Recording, y: None = None) -> Segmentation:
        """Segment ``recording`` (:func:`segment`); ``y`` is ignored (scikit-learn's form)."""
        seg = segment(
            recording,
            self.n_clusters,
            seed=self.seed,
            optimizer=self.optimizer,
            **self.settings,
        )
        self.segmentation_ = seg
        self.labels_ = seg.labels
        return seg

    def fit_predict(self, recording: Recording, y: None = None) -> np.ndarray:
        """Segment ``recording`` and return its labels (object ids, -1 unassigned)."""
        return self.fit(recording).labels
