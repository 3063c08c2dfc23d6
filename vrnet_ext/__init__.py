"""vrnet_ext: VRNet point-cloud registration on fused C++/OpenMP kernels."""
from vrnet_ext._extension import has_extension
from vrnet_ext import nn, ops
from vrnet_ext.model import VRNet, VRNetConfig, VRNetOutput
from vrnet_ext.pretrained import load_pretrained
from vrnet_ext.runtime import set_flush_denormal

__version__ = "0.1.0"
__all__ = ["ops", "nn", "VRNet", "VRNetConfig", "VRNetOutput", "has_extension", "load_pretrained",
           "set_flush_denormal", "__version__"]
