"""Preloaded by the measurement processes' fork server: importing this loads the compiled kernels.

Every child forked from that server then starts with them in memory (see
:mod:`service.runtime.measure_process`). Imported nowhere else.
"""

from service.core._kernels import detect_kernel, geometry_kernels, resection_kernel, roi_kernel
from service.core.targets.decode import warm_up as _decode_warm_up
from service.runtime import measure_process  # noqa: F401  (the children's entry point, imported once here)

for _kernels in (detect_kernel, geometry_kernels, resection_kernel, roi_kernel):
    _kernels.warm_up()
_decode_warm_up()
