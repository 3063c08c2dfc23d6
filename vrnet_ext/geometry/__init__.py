"""Clouds and their geometry: files (:mod:`io`, :mod:`atomic`), rigid transforms (:mod:`transforms`,
the one convention), voxel grids and sampling (:mod:`preprocessing`), FPFH at a voxel size and
feature matching (:mod:`features`) and the errors between transforms (:mod:`metrics`). Depends
only on :mod:`vrnet_ext.ops`."""
