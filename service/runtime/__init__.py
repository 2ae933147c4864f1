"""The running cell: acquisition, pairing with the robot, processing, sessions, the worker."""
