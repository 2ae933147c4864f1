"""Frames, rotations, the camera model and its OpenCV equivalent, similarity transforms."""
