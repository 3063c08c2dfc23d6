"""The VRNet model (``VRNetConfig`` imports without torch)."""
from vrnet_ext._lazy import lazy_attributes

__all__ = ["VRNet", "VRNetConfig", "VRNetOutput"]
__getattr__ = lazy_attributes(__name__, {"VRNetConfig": "vrnet_ext.model.config", "VRNet": "vrnet_ext.model.vrnet",
                                         "VRNetOutput": "vrnet_ext.model.vrnet"})
