"""ToF-sensor-to-camera calibration: the rig file, board and plane calibration, SLAM maps.

Camera intrinsics live in :mod:`deltar.camera`.
"""
