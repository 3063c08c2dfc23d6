"""Clouds and their geometry: files (:mod:`io`, :mod:`atomic`), rigid transforms (:mod:`transforms`,
the one convention), voxel grids and sampling (:mod:`preprocessing`), FPFH at a voxel size and
feature matching (:mod:`features`), the errors between transforms (:mod:`metrics`) and robust weights
of residuals (:mod:`robust`). Depends
only on :mod:`vrnet_ext.ops`."""
