"""Registration of real scans, as a package of small parts:

- :mod:`~vrnet_ext.registration.global_estimators`: an initial estimate with no prior (FPFH +
  RANSAC, FPFH + spatial consistency, FGR, the learned VRNet path, none) behind one interface,
  :class:`GlobalEstimator`;
- :mod:`~vrnet_ext.registration.ransac` and :mod:`~vrnet_ext.registration.fgr`: the feature
  matching and robust fits those use;
- :mod:`~vrnet_ext.registration.icp_steps`: ICP's local steps (point-to-point, point-to-plane,
  GICP) behind one interface, :class:`IcpStep`;
- :mod:`~vrnet_ext.registration.refinement`: ICP itself (:class:`IcpProblem` prepares a pair once for
  several starts), its settings (:class:`IcpSettings`) and
  :func:`fitness`, a score of any transform on a pair;
- :mod:`~vrnet_ext.registration.result`: the one result type, :class:`RegistrationResult`;
- :mod:`~vrnet_ext.registration.pipeline`: :func:`register`, global estimate + ICP + warnings;
- :mod:`~vrnet_ext.registration.degeneracy`: which directions the scans' geometry leaves free;
- :mod:`~vrnet_ext.registration.batch`: :func:`register_batch`, a manifest of pairs, resumable,
  sharded by torchrun;
- :mod:`~vrnet_ext.registration.multiway`: :func:`register_scene`, many scans of one scene into
  one frame (pairs, loop checks in :mod:`~vrnet_ext.registration.cycles`, a robust pose graph in
  :mod:`~vrnet_ext.registration.pose_graph`, a fused cloud); its errors against ground-truth poses:
  :mod:`~vrnet_ext.registration.scene_metrics`;
- :mod:`~vrnet_ext.registration.prepared`: both scans prepared once per registration
  (:class:`ScanPair`: voxels and FPFH shared by every estimator and ICP start);
- :mod:`~vrnet_ext.registration.budget`: the memory plan, from each estimator's own cost;
- :mod:`~vrnet_ext.registration.counts`: :class:`PointCounts`, how many points each stage works on
  (the names of the methods and ICP steps: :mod:`vrnet_ext.names`).

The names below load on first use (``import vrnet_ext.registration`` imports no torch).

Conventions (frames, 4x4 transforms) are those of :mod:`vrnet_ext.geometry.transforms`.
"""
from vrnet_ext._lazy import lazy_attributes

_EXPORTS = {
    **dict.fromkeys(("IcpStep", "make_icp_step"), "vrnet_ext.registration.icp_steps"),
    "PointCounts": "vrnet_ext.registration.counts",
    **dict.fromkeys(("DEFAULT_METHOD", "GLOBAL_ESTIMATORS", "ICP_STEPS"), "vrnet_ext.names"),
    **dict.fromkeys(("PreparedScan", "ScanPair"), "vrnet_ext.registration.prepared"),
    **dict.fromkeys(("Fgr", "FpfhRansac", "GlobalEstimator", "NoMotion", "ObjectNetwork", "SceneNetwork",
                     "SpatialConsistency", "make_global_estimator"), "vrnet_ext.registration.global_estimators"),
    **dict.fromkeys(("IcpFailure", "IcpProblem", "IcpSettings", "fitness", "icp"), "vrnet_ext.registration.refinement"),
    **dict.fromkeys(("RegistrationRun", "register", "register_prepared"), "vrnet_ext.registration.pipeline"),
    **dict.fromkeys(("SceneEdge", "SceneOptions", "SceneResult", "register_scene"), "vrnet_ext.registration.multiway"),
    **dict.fromkeys(("PoseEdge", "PoseGraphSettings", "PoseGraphSolution", "optimize_pose_graph"),
                    "vrnet_ext.registration.pose_graph"),
    "scene_errors": "vrnet_ext.registration.scene_metrics",
    "register_batch": "vrnet_ext.registration.batch",
    **dict.fromkeys(("RegistrationResult", "transform_errors"), "vrnet_ext.registration.result"),
}
__all__ = list(_EXPORTS)
__getattr__ = lazy_attributes(__name__, _EXPORTS)
