"""Localization-failure supervisor for an eye-in-hand Franka Panda.

Records a pose-estimation artifact (the PnP-RANSAC inlier count) against the
viewing-angle change, models it, and halts motion before localization fails.
"""

__version__ = "0.1.0"
