"""IMU/GNSS/speed fusion: the error-state EKF of paper 003 (Sec. 5, Alg. 1)."""
