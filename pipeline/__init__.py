"""vtcal: robot kinematic calibration from visual touch-up recordings."""

__version__ = "0.1.0"
