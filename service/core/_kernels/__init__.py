"""The compiled (numba) loops of the core; each module says what it computes and why by hand.

Every kernel is compiled with ``nogil=True``: the service measures in one thread while others
acquire, encode and send; a kernel that kept the interpreter's lock held them all (a fifth of the
lock's time at 500 frames/s was the ROI windows' kernel alone).
"""
