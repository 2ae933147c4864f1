"""The compiled (numba) loops of the core; each module says what it computes and why by hand."""
