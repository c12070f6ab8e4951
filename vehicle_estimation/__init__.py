"""vehicle_estimation: online estimation of vehicle mass, road slope and motion state.

Estimator cores (``vehicle_estimation.estimators``) are plain numpy/scipy/torch; the ROS 2
wrappers live in ``vehicle_estimation.ros``; the simulator in ``vehicle_estimation.sim``.
"""

__version__ = "0.1.0"
