"""Fringescope: fringe images from a structured-illumination laparoscope to metric depth."""

__version__ = "0.1.0"
