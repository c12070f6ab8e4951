"""Maths every estimator kind shares: rotations, geodesy."""
