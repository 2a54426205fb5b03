"""Recorded stereo from other tools: ASL/EuRoC folders and rosbags (ROS 1 ``.bag``, ROS 2 ``.db3``/``.mcap``).

sequence.py reads them as left/right pairs matched by timestamp (with the gaps and unmatched frames
counted) and their calibration where they carry one; camera.py is the service's camera source over a
sequence (``camera.source = "replay"`` with such a ``replay_path``). Replaying a sequence through the
pipeline into per-frame records and the review report (``companion process --sequence``) is
:mod:`companion.view.replay`, above the service it borrows the preview's thresholds from.
"""
