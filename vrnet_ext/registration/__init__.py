"""Registration of real scans, as a package of small parts:

- :mod:`~vrnet_ext.registration.global_estimators`: an initial estimate with no prior (FPFH +
  RANSAC, FPFH + spatial consistency, FGR, the learned VRNet path, none) behind one interface,
  :class:`GlobalEstimator`;
- :mod:`~vrnet_ext.registration.ransac` and :mod:`~vrnet_ext.registration.fgr`: the feature
  matching and robust fits those use;
- :mod:`~vrnet_ext.registration.estimators`: ICP's local steps (point-to-point, point-to-plane,
  GICP) behind one interface, :class:`Estimator`;
- :mod:`~vrnet_ext.registration.refinement`: ICP itself (:class:`IcpProblem` prepares a pair once for
  several starts), its settings (:class:`IcpSettings`) and
  :func:`fitness`, a score of any transform on a pair;
- :mod:`~vrnet_ext.registration.result`: the one result type, :class:`RegistrationResult`;
- :mod:`~vrnet_ext.registration.pipeline`: :func:`register`, global estimate + ICP + warnings.

Conventions (frames, 4x4 transforms) are those of :mod:`vrnet_ext.geometry.transforms`.
"""
from vrnet_ext.registration.estimators import ESTIMATORS, Estimator, make_estimator
from vrnet_ext.registration.global_estimators import (GLOBAL_ESTIMATORS, Fgr, FpfhRansac, GlobalEstimator, NoMotion,
                                                      ObjectNetwork, SceneNetwork, SpatialConsistency,
                                                      make_global_estimator)
from vrnet_ext.registration.refinement import IcpFailure, IcpProblem, IcpSettings, fitness, icp
from vrnet_ext.registration.pipeline import register
from vrnet_ext.registration.result import RegistrationResult, transform_errors

__all__ = ["ESTIMATORS", "Estimator", "make_estimator", "GLOBAL_ESTIMATORS", "GlobalEstimator", "FpfhRansac", "Fgr",
           "NoMotion", "ObjectNetwork", "SceneNetwork", "SpatialConsistency", "make_global_estimator", "IcpFailure",
           "IcpProblem", "IcpSettings", "fitness", "icp", "register", "RegistrationResult", "transform_errors"]
