// Operator schemas of the vrnet_ext library and the Python entry point of vrnet_ext._C.
// Backends register kernels with TORCH_LIBRARY_IMPL in csrc/<op>/; fake (meta) kernels and
// autograd formulas are registered from Python (vrnet_ext/ops/<op>.py).
#include <Python.h>
#include <torch/library.h>

#include "common/common.h"
#include "common/schemas.h"

TORCH_LIBRARY(vrnet_ext, m) {
#define VRNET_DEFINE(schema) m.def(schema);
  VRNET_OP_SCHEMAS(VRNET_DEFINE)
#undef VRNET_DEFINE
}

namespace {

// _suspend_value_checks(delta): vrnet_ext.ops.trusted_values() entering (+1) or leaving (-1).
PyObject* suspend_value_checks(PyObject*, PyObject* delta) {
  const long change = PyLong_AsLong(delta);
  if (change == -1 && PyErr_Occurred()) return nullptr;
  vrnet::value_checks_suspended() += static_cast<int>(change);
  Py_RETURN_NONE;
}

PyMethodDef methods[] = {
    {"_suspend_value_checks", suspend_value_checks, METH_O,
     "Enter (+1) or leave (-1) a region where the kernels skip value checks on accelerators (this thread)."},
    {nullptr, nullptr, 0, nullptr}};

}  // namespace

extern "C" PyObject* PyInit__C(void) {
  static struct PyModuleDef module_def = {PyModuleDef_HEAD_INIT, "_C",
                                          "vrnet_ext compiled kernels (ops live in torch.ops.vrnet_ext)",
                                          -1, methods};
  return PyModule_Create(&module_def);
}
