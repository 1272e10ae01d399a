"""ROS-free core of equidiff_ros: geometry and config at the top; wire, perception, cameras, models, policy,
training, data, control, robots, twin, lab, calibration, viz, benches and runtime as packages
(docs/modules.md, "Core modules")."""

__version__ = "0.1.0"
