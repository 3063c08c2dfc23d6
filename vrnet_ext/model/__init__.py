"""The VRNet model."""
from vrnet_ext.model.config import VRNetConfig
from vrnet_ext.model.vrnet import VRNet, VRNetOutput

__all__ = ["VRNet", "VRNetConfig", "VRNetOutput"]
