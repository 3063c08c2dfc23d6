// The operator schemas of the vrnet_ext library, as an X-macro: VRNET_OP_SCHEMAS(X) calls X(schema)
// once per op. Defined once here for the library itself (csrc/registration.cpp) and for the test
// library vrnet_ext_emu that runs the CUDA glue under the CPU emulator (tests/cuda_emu/runtime.cpp).
#pragma once

#define VRNET_OP_SCHEMAS(X) \
  X("knn(Tensor query, Tensor ref, int k, bool exclude_self) -> (Tensor, Tensor)") \
  X("knn_backward(Tensor grad_dist2, Tensor query, Tensor ref, Tensor idx) -> (Tensor, Tensor)") \
  X("knn_unproven_rows(Tensor query, Tensor ref, int k, bool exclude_self) -> Tensor") \
  X("edge_features(Tensor x, Tensor idx) -> Tensor") \
  X("edge_features_backward(Tensor grad_out, Tensor idx, int num_points) -> Tensor") \
  X("gather_reduce(Tensor values, Tensor idx, str reduce) -> (Tensor, Tensor)") \
  X("gather_reduce_backward(Tensor grad_out, Tensor idx, Tensor arg, str reduce, int num_values) -> Tensor") \
  X("edge_norm_max(Tensor projections, Tensor idx, Tensor? weight, Tensor? bias, Tensor? running_mean, Tensor? running_var, float eps, float negative_slope) -> (Tensor, Tensor, Tensor, Tensor)") \
  X("edge_norm_max_backward(Tensor grad_out, Tensor projections, Tensor idx, Tensor arg, Tensor? weight, Tensor? bias, Tensor mean, Tensor var, bool batch_stats, float eps, float negative_slope) -> (Tensor, Tensor, Tensor)") \
  X("svd3x3(Tensor A) -> (Tensor, Tensor, Tensor)") \
  X("svd3x3_backward(Tensor grad_U, Tensor grad_S, Tensor grad_V, Tensor U, Tensor S, Tensor V) -> Tensor") \
  X("kabsch(Tensor src, Tensor tgt, Tensor weights) -> (Tensor, Tensor)") \
  X("kabsch_backward(Tensor grad_R, Tensor grad_t, Tensor src, Tensor tgt, Tensor weights) -> (Tensor, Tensor, Tensor)") \
  X("robust_kabsch(Tensor src, Tensor tgt, Tensor weights, int iterations, str kernel, float scale, float min_scale) -> (Tensor, Tensor)") \
  X("pairwise_distance_loss(Tensor x, Tensor y) -> Tensor") \
  X("pairwise_distance_loss_backward(Tensor grad_loss, Tensor x, Tensor y, Tensor loss) -> (Tensor, Tensor)") \
  X("soft_match(Tensor query, Tensor key, Tensor values, float scale) -> (Tensor, Tensor, Tensor)") \
  X("soft_match_backward(Tensor grad_out, Tensor grad_lse, Tensor query, Tensor key, Tensor values, Tensor out, Tensor lse, float scale) -> (Tensor, Tensor, Tensor)") \
  X("soft_match_flash(Tensor query, Tensor key, Tensor values, float scale, int passes, int target_blocks) -> (Tensor, Tensor, Tensor)") \
  X("soft_match_flash_backward(Tensor grad_out, Tensor grad_lse, Tensor query, Tensor key, Tensor values, Tensor out, Tensor lse, float scale, int passes) -> (Tensor, Tensor, Tensor)") \
  X("normals(Tensor points, Tensor idx, float[] viewpoint) -> Tensor") \
  X("fpfh(Tensor points, Tensor normals, Tensor idx, Tensor dist2, float radius) -> Tensor") \
  X("voxel_downsample(Tensor points, float voxel_size) -> Tensor") \
  X("spatial_consistency(Tensor src, Tensor tgt, float tolerance, float inlier_threshold, int seeds, int consensus) -> (Tensor, Tensor)") \
  X("attention(Tensor q, Tensor k, Tensor v, float scale) -> Tensor")
