"""Clouds and their geometry: files (:mod:`io`, :mod:`atomic`), rigid transforms (:mod:`transforms`,
the one convention), voxel grids and sampling (:mod:`preprocessing`), FPFH at a voxel size and
feature matching (:mod:`features`), the errors between transforms (:mod:`metrics`) and how near an
estimate brings two clouds, with a robust ICP that brings them nearer (:mod:`alignment`). Depends
only on :mod:`vrnet_ext.ops`."""
