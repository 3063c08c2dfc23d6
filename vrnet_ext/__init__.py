"""vrnet_ext: VRNet point-cloud registration on fused C++/OpenMP kernels.

Attributes load on first use (``vrnet_ext.ops`` imports torch and the compiled kernels)."""
from vrnet_ext import _moved
from vrnet_ext._lazy import lazy_attributes

_moved.install()  # old module paths (vrnet_ext.io, ...) still import, with a DeprecationWarning

__version__ = "0.2.0.dev0"
__all__ = ["register", "register_scene", "RegistrationResult", "ops", "nn", "VRNet", "VRNetConfig", "VRNetOutput", "has_extension",
           "load_pretrained", "set_flush_denormal", "__version__"]
__getattr__ = lazy_attributes(__name__, {
    "register": "vrnet_ext.registration", "register_scene": "vrnet_ext.registration",
    "RegistrationResult": "vrnet_ext.registration",
    "ops": "vrnet_ext.ops", "nn": "vrnet_ext.nn", "VRNet": "vrnet_ext.model", "VRNetConfig": "vrnet_ext.model",
    "VRNetOutput": "vrnet_ext.model", "has_extension": "vrnet_ext._extension",
    "load_pretrained": "vrnet_ext.model.pretrained", "set_flush_denormal": "vrnet_ext.runtime",
})
