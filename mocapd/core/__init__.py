"""Pure math of mocapd: no I/O, no asyncio, no clocks (a test enforces this).

Modules: ``rotations`` (quaternions, rotation vectors, SO(3)), ``skeleton`` (the 21-bone skeleton and its
sizing), ``kinematics`` (forward kinematics and its Jacobians), ``camera`` (pinhole + distortion, projection,
triangulation), ``imu`` (IMU mounting model, Eq. 8 and 12 of seed 003), ``keypoints`` (keypoint sets as track
targets), ``loss`` (robust losses), ``prior`` (PCA pose prior), ``terms`` (the cost terms of seed 003 §3.2),
``solver`` (Levenberg–Marquardt).
"""
