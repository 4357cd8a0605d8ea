"""clsplat: differentiable Gaussian splatting on any OpenCL device.

The front door is :func:`rasterization` (gsplat's interface). :mod:`clsplat.reference` is the
dense float64 PyTorch implementation of the same semantics, used as the accuracy baseline.
"""
from .config import RenderConfig
from .rendering import rasterization
from .runtime import BuildError, DeviceError, describe_devices, get_runtime

__all__ = ["rasterization", "RenderConfig", "get_runtime", "describe_devices", "BuildError",
           "DeviceError"]
__version__ = "0.1.0"
