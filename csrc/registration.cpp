// Operator schemas of the vrnet_ext library and the Python entry point of vrnet_ext._C.
// Backends register kernels with TORCH_LIBRARY_IMPL in csrc/<op>/; fake (meta) kernels and
// autograd formulas are registered from Python (vrnet_ext/ops/<op>.py).
#include <Python.h>
#include <torch/library.h>

TORCH_LIBRARY(vrnet_ext, m) {
  m.def("knn(Tensor query, Tensor ref, int k, bool exclude_self) -> (Tensor, Tensor)");
  m.def("knn_backward(Tensor grad_dist2, Tensor query, Tensor ref, Tensor idx) -> (Tensor, Tensor)");
  m.def("edge_features(Tensor x, Tensor idx) -> Tensor");
  m.def("edge_features_backward(Tensor grad_out, Tensor idx, int num_points) -> Tensor");
  m.def("gather_reduce(Tensor values, Tensor idx, str reduce) -> (Tensor, Tensor)");
  m.def("gather_reduce_backward(Tensor grad_out, Tensor idx, Tensor arg, str reduce, int num_values) -> Tensor");
  m.def("edge_norm_max(Tensor projections, Tensor idx, Tensor? weight, Tensor? bias, Tensor? running_mean, Tensor? running_var, float eps, float negative_slope) -> (Tensor, Tensor, Tensor, Tensor)");
  m.def("edge_norm_max_backward(Tensor grad_out, Tensor projections, Tensor idx, Tensor arg, Tensor? weight, Tensor? bias, Tensor mean, Tensor var, bool batch_stats, float eps, float negative_slope) -> (Tensor, Tensor, Tensor)");
  m.def("svd3x3(Tensor A) -> (Tensor, Tensor, Tensor)");
  m.def("svd3x3_backward(Tensor grad_U, Tensor grad_S, Tensor grad_V, Tensor U, Tensor S, Tensor V) -> Tensor");
  m.def("kabsch(Tensor src, Tensor tgt, Tensor weights) -> (Tensor, Tensor)");
  m.def("kabsch_backward(Tensor grad_R, Tensor grad_t, Tensor src, Tensor tgt, Tensor weights) -> (Tensor, Tensor, Tensor)");
  m.def("pairwise_distance_loss(Tensor x, Tensor y) -> Tensor");
  m.def("pairwise_distance_loss_backward(Tensor grad_loss, Tensor x, Tensor y, Tensor loss) -> (Tensor, Tensor)");
  m.def("soft_match(Tensor query, Tensor key, Tensor values, float scale) -> (Tensor, Tensor, Tensor)");
  m.def("soft_match_backward(Tensor grad_out, Tensor grad_lse, Tensor query, Tensor key, Tensor values, Tensor out, Tensor lse, float scale) -> (Tensor, Tensor, Tensor)");
  m.def("normals(Tensor points, Tensor idx, float[] viewpoint) -> Tensor");
  m.def("fpfh(Tensor points, Tensor normals, Tensor idx, Tensor dist2, float radius) -> Tensor");
  m.def("voxel_downsample(Tensor points, float voxel_size) -> Tensor");
}

extern "C" PyObject* PyInit__C(void) {
  static struct PyModuleDef module_def = {PyModuleDef_HEAD_INIT, "_C",
                                          "vrnet_ext compiled kernels (ops live in torch.ops.vrnet_ext)",
                                          -1, nullptr};
  return PyModule_Create(&module_def);
}
