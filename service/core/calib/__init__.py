"""Calibrations: the camera (bundle), the rig, the hand-eye."""
