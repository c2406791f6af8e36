"""dmais_pipe: calibration and pose estimation for a divergent multi-aperture imaging system."""

__version__ = "0.1.0"
