"""Registration building blocks (the pipeline itself is :func:`vrnet_ext.register.register`).

:mod:`vrnet_ext.registration.estimators`: ICP's local refinement steps (point-to-point,
point-to-plane, GICP) behind one interface.
"""
from vrnet_ext.registration.estimators import ESTIMATORS, make_estimator

__all__ = ["ESTIMATORS", "make_estimator"]
