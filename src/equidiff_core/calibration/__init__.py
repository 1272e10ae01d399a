"""Camera extrinsic calibration (ROS-free): a ChArUco board on the hand, every camera's T_base_optical.

* ``board``: the board's geometry, a printable PDF/PNG of exact size, detection (OpenCV aruco)
* ``plan``: TCP poses in the workspace from which the cameras see the board
* ``capture``: the capture loop (move, settle, detect) for a franky arm and RealSense colour
* ``operator``: SpaceMouse-driven poses instead of planned ones
* ``solve``: closed-form eye-to-hand per camera, then joint reprojection refinement
* ``labfile``: the calibrated lab YAML (never overwritten silently)
* ``check``: each camera's misalignment in mm against the other clouds and the fingertips
* ``job``: the jobs of ``equidiff calibrate cameras`` and ``check``, lab or twin (``run_camera_calibration``, ``run_calibration_check``)

In the digital twin, against its ground truth: ``twin.calibration``.
Commands: ``equidiff calibrate cameras`` and ``equidiff calibrate check`` (docs/perception.md).
"""
