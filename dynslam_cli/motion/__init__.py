"""Learning to forget: instance segmentation, embeddings, the continual motion classifier.

Public API (import from the submodules to keep `import dynslam_cli.motion` light):

* ``module.MotionModule`` -- what the SLAM loop calls (observe, check_and_update, keyframes, state)
* ``types`` -- ``Segmentation``, ``FrameInstances``, ``CheckResult``, ``UpdateRecord``
* segmenters: ``segment_geometric.GeometricSegmenter``, ``segment_yolo.YoloSegSegmenter``,
  ``segmenters.make_segmenter``, ``segment_base.prune_parts`` / ``masks_to_ids``
* encoders: ``encode_effnet.EffNetLite0Encoder``, ``encode_onnx.OnnxEncoder`` (presets onnx, clip,
  dino, blip), ``encode_hist.ColorHistEncoder``, ``encoders.make_encoder``
* ``classifier`` -- ``MotionClassifier``, ``ReplayBuffer``, ``update_with_replay``, prior files
* ``check.inconsistency_check`` -- the bidirectional depth check; ``checkable.checkable_depth`` /
  ``closest_rendered`` -- what of the observation the map can judge
* ``stayed.stayed_put`` -- instances that stayed put (never labelled moving)
* ``forget`` -- ``refresh_keyframes`` (re-mask keyframe rays after a classifier update),
  ``departed_points`` with ``forget_near`` (keyframe rays on the surface of what the check saw leave),
  ``DepartedPlaces`` (where it saw something leave) and ``departed_surface`` (what the mesh leaves out)
* ``prior.fit_prior`` -- ``dynslam prior fit``
"""
