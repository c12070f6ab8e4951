"""Vehicle motion state: CKF / VB-ACKF (paper 004), AO-UKF + GA-BPNN (paper 002) on a shared car model."""
