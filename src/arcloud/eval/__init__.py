"""Evaluation: the standard 3D detection metric and pictures of the results.

- ``arcloud.eval.metrics``: mAP at 3D IoU thresholds on axis-aligned boxes, as the ScanNet evaluation
  (VoteNet ``eval_det.py``, mmdetection3d ``indoor_eval``) computes it.
- ``arcloud.eval.plot``: a top-down PNG of ground-truth and predicted boxes, and boxes drawn into frames.
- ``arcloud.eval.charts``: matplotlib charts of the figures (AP per class, precision-recall curves, mAP against K).

Import the submodules directly; nothing is imported here so that ``import arcloud.eval`` stays light.
"""
