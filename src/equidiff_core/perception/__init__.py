"""Perception: from the cameras' clouds to the policy's observation (no ROS).

* ``voxels``: coloured point clouds fused into the (4, R, R, R) uint8 voxel grid
* ``sync``: approximate-time matching of the camera streams, staleness, phase-locked publishing
* ``fusion``: the clouds fused into grids, voxel_node's rule live and offline (``revoxelize_bag``)
* ``observation``: the policy's input built one way from raw robot data (training, policy_node, twin)
"""
