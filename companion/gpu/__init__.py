"""CuPy backend: the stereo pipeline's expensive half on a CUDA GPU.

:class:`CupyRegionEstimator` implements the :class:`~companion.core.pipeline.RegionEstimator`
contract with CUDA kernels (``kernels/stereo.cu``: grey, remap, SAD block matching; ``kernels/sgm.cu``:
census + semi-global matching) that reproduce the CPU reference bit for bit.
Importing this package does not import CuPy; building an estimator does.
"""

from companion.gpu.estimator import CupyRegionEstimator

__all__ = ["CupyRegionEstimator"]
