"""Errors raised by pothole_detector; every message says what to do about it."""

from __future__ import annotations


class PotholeError(Exception):
    """Base class of every error this package raises on purpose."""


class ConfigError(PotholeError):
    """A parameter is unknown, of the wrong type or outside its range."""


class CalibrationError(PotholeError):
    """Camera calibration is missing, inconsistent or not a rectified stereo pair."""


class InputError(PotholeError):
    """An input image or file cannot be used (missing, wrong size, wrong encoding)."""


class NoTextureError(InputError):
    """The stereo matcher found too few valid disparities to work with."""


class NoRoadError(PotholeError):
    """No road plane explains enough of the disparity map; nothing is detected."""


class BackendError(PotholeError):
    """The requested compute backend is not available on this machine."""
