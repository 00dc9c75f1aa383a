"""Accuracy suites that can fail: generated rooms (``sim``), ScanNet renders with randomised walks and
mask faults (``scannet``) and the real 7-Scenes sequence against hand-checked boxes (``sevenscenes``).

Every suite returns the same record (``arcloud.accuracy.common``): one entry per case (a room and a
walk, a render, a real sequence), each case in the ``tune`` or the ``report`` split, and a summary per
split with the mean and the worst case of every figure. ``bench/bench_accuracy.py`` runs them all
(``make accuracy``)."""
