"""From a rig to recordings and back: sensor drivers, recording, replay, the viewer.

``drivers`` reads a real (or simulated) ToF sensor and camera, ``record`` writes what
they capture as a recording folder or a ROS 2 bag, ``replay`` and ``bag_replay`` run a
depth estimator over a recording or a bag, ``viewer`` streams frames to rerun. The
estimator itself is :mod:`deltar.inference`.
"""
