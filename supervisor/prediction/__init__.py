"""Artifact model (scaled EMG), its variants, and the predictors built on it."""

from supervisor.prediction.base import Prediction, Predictor
from supervisor.prediction.predictors import PREDICTORS, make_predictor

__all__ = ["PREDICTORS", "Prediction", "Predictor", "make_predictor"]
