"""Each numba kernel of ``service/core/_kernels`` against an independent NumPy / SciPy / OpenCV reference."""
