"""Stereo road pothole detection: GPT-SGM, disparity transformation, SLIC, 2D-histogram
threshold, per-pothole 3D (Fan et al., T-CYB)."""

from __future__ import annotations

__version__ = "0.1.0"
