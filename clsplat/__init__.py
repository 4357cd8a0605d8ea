"""clsplat: differentiable Gaussian splatting on any OpenCL device.

The front door is :func:`rasterization` (gsplat's interface). :mod:`clsplat.reference` is the
float64 PyTorch implementation of gsplat's semantics, used as the accuracy baseline;
:mod:`clsplat.strategy` holds torch ports of gsplat's densification strategies.
"""
from . import threads as _threads  # noqa: F401  first: sets the OpenMP wait policy before torch loads
from .config import RenderConfig
from .rendering import RollingShutterType, rasterization
from .runtime import BuildError, DeviceError, describe_devices, get_runtime

__all__ = ["rasterization", "RollingShutterType", "RenderConfig", "get_runtime", "describe_devices", "BuildError",
           "DeviceError"]
__version__ = "0.1.0"
