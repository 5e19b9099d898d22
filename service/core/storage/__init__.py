"""The data directory: atomic files, the calibration and parameter stores."""
