"""Vehicle mass: RLS (paper 003), FFRLS (paper 004), TA-AEKF (paper 000), OBD calibration, wind."""
