"""Estimators of the rendering equation and its derivative, one term per module."""
