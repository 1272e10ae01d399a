"""equidiff_ros: one ament_python package holding the ROS-free core and the rclpy nodes.

`colcon build` installs node executables under lib/equidiff_ros/ (see setup.cfg);
`pip install -e .` installs the same executables plus the `equidiff` CLI on PATH.
"""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "equidiff_ros"
NODES = ["camera_node", "voxel_node", "policy_node", "franka_node", "teleop_node", "recorder_node", "twin_node"]

setup(
    name=PACKAGE,
    version="0.1.0",
    description="Equivariant Diffusion Policy (EquiDiff) on ROS 2 Jazzy: Franka, RealSense, SpaceMouse, MCAP, rerun, MuJoCo twin",
    license="MIT",
    python_requires=">=3.10",
    package_dir={"": "src"},
    packages=find_packages("src"),
    package_data={"equidiff_core": ["assets/*", "assets/**/*"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.py")),
        # the policy and its record; its resumable training state (*.ckpt) stays in the source tree
        (
            f"share/{PACKAGE}/checkpoints/twin_compact",
            [p for p in glob("checkpoints/twin_compact/*") if not p.endswith(".ckpt")],
        ),
    ],
    # Installed by apt on a ROS machine, by scripts/setup.sh (PyPI ros-jazzy-* wheels) elsewhere.
    install_requires=[
        "numpy>=2",
        "scipy",
        "pyyaml",
        "torch>=2.6",  # weights_only loading has a known bypass before 2.6 (CVE-2025-32434)
        "diffusers>=0.30",
        "escnn==1.0.11",
        "rosbags>=0.10",
        "mcap>=1.2",
        "tqdm",
        "matplotlib",
        "safetensors",
        # camera_node's JPEG colour images, their decoding in viz and export (also ChArUco detection)
        "opencv-contrib-python-headless==5.0.0.93",
        "pyarrow",  # export lerobot: parquet
    ],
    extras_require={
        # prompt_toolkit: `equidiff lab`, the operator's terminal screen
        "ros": ["ros-jazzy-rclpy[fastrtps]", "ros-jazzy-common-interfaces", "prompt_toolkit>=3.0.36"],
        "viz": ["rerun-sdk>=0.41"],
        "robot": ["franky-control>=2.0"],
        "twin": ["franky-sim>=1.0.4", "franky-control>=2.0", "mujoco"],
        "realsense": ["pyrealsense2"],
        "spacemouse": ["pyspacemouse", "hidapi"],
        "open3d": ["open3d-cpu==0.20.0"],
        "calib": ["opencv-contrib-python-headless==5.0.0.93"],  # ChArUco detection for camera calibration
        # export lerobot: AV1 mp4 as LeRobot encodes it (PyAV's wheel bundles FFmpeg with libsvtav1 and dav1d)
        "export": ["av==18.1.0"],
        "dev": ["pytest", "pytest-timeout", "hypothesis", "colcon-core==0.21.3", "colcon-ros==0.5.0",
                "colcon-python-setup-py", "mcap-ros2-support", "ruff"],
    },
    entry_points={
        "console_scripts": [f"{node} = equidiff_ros.{node}:main" for node in NODES]
        + ["equidiff = equidiff_ros.cli:main", "equidiff_composed = equidiff_ros.composed:main"],
    },
)
