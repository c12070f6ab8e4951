"""Estimator cores: numpy/scipy/torch only, no ROS import; one module per method, testable on arrays."""
