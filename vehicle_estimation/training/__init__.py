"""Data and training of the shipped models, and the per-vehicle calibration (paper 003 training phase)."""
