"""ROS-free core of equidiff_ros: geometry, voxels, models, diffusion, data, training, twin, viz."""

__version__ = "0.1.0"
