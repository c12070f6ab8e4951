"""ament_python package vehicle_estimation (builds with colcon and installs with pip)."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "vehicle_estimation"

NODES = {
    "fusion_node": "vehicle_estimation.ros.fusion_node:main",
    "slope_node": "vehicle_estimation.ros.slope_node:main",
    "state_node": "vehicle_estimation.ros.state_node:main",
    "mass_node": "vehicle_estimation.ros.mass_node:main",
}

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    package_data={PACKAGE: ["sim/data/*.csv", "models/*"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml", "README.md"]),
        (f"share/{PACKAGE}/params", glob("params/*.yaml")),
        (f"share/{PACKAGE}/params/import_maps", glob("params/import_maps/*.yaml")),
    ],
    python_requires=">=3.10",
    install_requires=["setuptools", "numpy", "scipy", "pyyaml", "rosbags>=0.10", "matplotlib", "pymap3d", "tqdm"],
    extras_require={
        # What a machine without a ROS 2 install needs: rclpy and the message packages as wheels.
        "pypi": [
            "ros-jazzy-rclpy[fastrtps]",
            "ros-jazzy-common-interfaces",
            "torch==2.13.0",
            "safetensors",
        ],
        "test": ["pytest", "pytest-xdist", "hypothesis", "filterpy", "colcon-common-extensions", "mypy", "ruff", "commonroad-vehicle-models==3.0.2",
                 "fastsim==3.1.0", "wltp==0.1.2a0", "dask[distributed]>=2024.8", "numba>=0.60"],
        # Compiled filter kernels (numba): the same estimates, the state and fusion steps 5-18x faster.
        "fast": ["numba>=0.60"],
        # Fleet-scale batch replay (`vehicle-estimation batch`) on a Dask cluster.
        "fleet": ["dask[distributed]>=2024.8"],
        "validation": ["commonroad-vehicle-models==3.0.2", "fastsim==3.1.0", "wltp==0.1.2a0"],
    },
    zip_safe=True,
    maintainer="vehicle_estimation developers",
    maintainer_email="vehicle-estimation@users.noreply.github.com",
    description="Online estimation of vehicle mass, road slope and motion state from IMU, GNSS and CAN/OBD-II.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [f"{name} = {target}" for name, target in NODES.items()]
        + ["vehicle-estimation = vehicle_estimation.cli:main"],
    },
)
