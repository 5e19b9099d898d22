"""The axes and their motions: devices, controllers, homing, calibration, plausibility."""
