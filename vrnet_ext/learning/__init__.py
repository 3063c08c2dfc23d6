"""Training and evaluation: the options (:mod:`config`), the two-stage ModelNet40 loop
(:mod:`train`), losses, evaluation, warm starts, the scene model's self-supervised training
(:mod:`scene_training`) and training curves (:mod:`curves`). Never imports
:mod:`vrnet_ext.registration`."""
