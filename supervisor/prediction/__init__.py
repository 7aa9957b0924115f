"""Artifact model (scaled EMG), its variants, and the predictors built on it."""

from supervisor.prediction.predictors import PREDICTORS, Prediction, make_predictor

__all__ = ["PREDICTORS", "Prediction", "make_predictor"]
