"""KeypointDeformer training in PyTorch (the only package besides kpd.export that imports torch).

- ``nets``: Φ (keypoint predictor), Γ (influence predictor), W_C and the cage template in one module
  (:class:`KeypointDeformer`; state-dict keys as the authors' checkpoints, docs/method.md §16).
- ``ops``: batched chamfer, farthest point sampling, the M-nearest mask, cage deformation, mean value coordinates.
- ``losses``: L_sim, L_kpt, L_inf (docs/method.md §6).
- ``trainer``: :class:`TrainConfig`, :class:`Trainer`, :func:`train` (checkpoints, exact resume, records).
- ``distributed``: torchrun data parallelism (the world of a rank, rank-0-first turns, the checkpoint broadcast).
- ``predictor``: :class:`CheckpointPredictor` (keypoints, influence, alignment from a checkpoint).
- ``evaluate``: alignment chamfer (paper Fig. 7) and label-free keypoint quality.
"""
