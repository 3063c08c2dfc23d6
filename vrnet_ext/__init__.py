"""vrnet_ext: VRNet point-cloud registration on fused C++/OpenMP kernels."""
from vrnet_ext._extension import has_extension
from vrnet_ext import nn, ops
from vrnet_ext.model import VRNet, VRNetConfig, VRNetOutput

__version__ = "0.1.0"
__all__ = ["ops", "nn", "VRNet", "VRNetConfig", "VRNetOutput", "has_extension", "__version__"]
