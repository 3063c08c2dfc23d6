// Operator schemas of the vrnet_ext library and the Python entry point of vrnet_ext._C.
// Backends register kernels with TORCH_LIBRARY_IMPL in csrc/<op>/; fake (meta) kernels and
// autograd formulas are registered from Python (vrnet_ext/ops/<op>.py).
#include <Python.h>
#include <torch/library.h>

#include "common/schemas.h"

TORCH_LIBRARY(vrnet_ext, m) {
#define VRNET_DEFINE(schema) m.def(schema);
  VRNET_OP_SCHEMAS(VRNET_DEFINE)
#undef VRNET_DEFINE
}

extern "C" PyObject* PyInit__C(void) {
  static struct PyModuleDef module_def = {PyModuleDef_HEAD_INIT, "_C",
                                          "vrnet_ext compiled kernels (ops live in torch.ops.vrnet_ext)",
                                          -1, nullptr};
  return PyModule_Create(&module_def);
}
